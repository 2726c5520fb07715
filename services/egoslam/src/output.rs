//! Result files: TUM trajectories, PLY point clouds, egoslam calibration YAML.

use anyhow::Context;
use egoslam_geometry::{PinholeRadtan, StampedPose};
use std::io::Write;
use std::path::{Path, PathBuf};

/// The folder of a run's internal state (checkpoint, journal, logs, marks) inside its
/// output folder, apart from the results the user asked for (docs/durability.md).
pub fn state_dir(out: &Path) -> PathBuf {
    out.join("state")
}

/// [`state_dir`], created owner-only (0700: egocentric video's descriptors and patches are
/// private) if it is not there yet.
pub fn create_state_dir(out: &Path) -> anyhow::Result<PathBuf> {
    use std::os::unix::fs::DirBuilderExt;
    let dir = state_dir(out);
    std::fs::DirBuilder::new()
        .recursive(true)
        .mode(0o700)
        .create(&dir)
        .with_context(|| format!("creating {}", dir.display()))?;
    Ok(dir)
}

/// Writes `bytes` to `path` via a temporary file and a rename, so readers (and a crash)
/// only ever see the old or the new complete file. The temporary file is `path` with
/// `.tmp` appended: one per target file, so processes writing different files of one
/// folder (`keyframes.tum` by the merger, `keyframes.log` by the frontend) never share it.
pub fn write_atomically(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".tmp");
    let tmp = std::path::PathBuf::from(tmp);
    let mut f =
        std::fs::File::create(&tmp).with_context(|| format!("creating {}", tmp.display()))?;
    f.write_all(bytes)
        .with_context(|| format!("writing {}", tmp.display()))?;
    f.sync_all().ok();
    std::fs::rename(&tmp, path).with_context(|| format!("renaming to {}", path.display()))
}

/// Replaces the file at `path` with `prefix` followed by its bytes from `offset` on, via
/// [`write_atomically`]: how an append-only log drops its head (the journal with a new
/// header, the keyframe log with none). Only the kept tail is read.
pub fn keep_tail_atomically(path: &Path, offset: u64, prefix: &[u8]) -> anyhow::Result<()> {
    use std::io::{Read, Seek};
    let mut bytes = prefix.to_vec();
    let mut file =
        std::fs::File::open(path).with_context(|| format!("opening {}", path.display()))?;
    file.seek(std::io::SeekFrom::Start(offset))
        .and_then(|_| file.read_to_end(&mut bytes))
        .with_context(|| format!("reading {}", path.display()))?;
    write_atomically(path, &bytes)
}

/// TUM trajectory text: `timestamp tx ty tz qx qy qz qw`.
pub fn tum_text(poses: &[StampedPose]) -> String {
    let mut s = String::from("# timestamp tx ty tz qx qy qz qw (world_from_camera)\n");
    for p in poses {
        let q = p.rotation.quaternion();
        s.push_str(&format!(
            "{:.6} {:.6} {:.6} {:.6} {:.6} {:.6} {:.6} {:.6}\n",
            p.timestamp, p.position.x, p.position.y, p.position.z, q.i, q.j, q.k, q.w
        ));
    }
    s
}

/// The calibration in egoslam's own YAML format (docs/config.md).
pub fn camera_yaml(camera: &PinholeRadtan, origin: &Path) -> String {
    let d = camera.distortion;
    format!(
        "# resolved by egoslam from {}\nmodel: {}\nwidth: {}\nheight: {}\nfx: {}\nfy: {}\ncx: {}\ncy: {}\ndistortion: [{}, {}, {}, {}, {}]\n",
        origin.display(),
        camera.lens.name(),
        camera.width,
        camera.height,
        camera.fx,
        camera.fy,
        camera.cx,
        camera.cy,
        d[0],
        d[1],
        d[2],
        d[3],
        d[4]
    )
}
