//! The rolling-shutter readout a frontend estimated online (`--rolling-shutter-ms auto` on a
//! live stream), kept in the state folder: a restarted frontend goes on with it instead of
//! estimating again, and the merger saves it with the map.

use std::path::Path;

/// File (in the state folder) with the readout, milliseconds, as text.
pub const FILE_NAME: &str = "frontend.readout";

/// Longest readout that can be given, ms (a frame interval at 10 fps).
pub const MAX_READOUT_MS: f64 = 100.0;

/// The readout (ms) a frontend of the run writing to `out` estimated and saved, if any (a
/// missing, unreadable or out-of-range file is none).
pub fn read(out: &Path) -> Option<f64> {
    std::fs::read_to_string(crate::state_dir(out).join(FILE_NAME))
        .ok()
        .and_then(|t| t.trim().parse::<f64>().ok())
        .filter(|ms| (0.0..=MAX_READOUT_MS).contains(ms))
}

/// Saves the readout (ms) for [`read`], atomically.
pub fn write(out: &Path, readout_ms: f64) -> crate::Result<()> {
    crate::write_atomically(
        &crate::state_dir(out).join(FILE_NAME),
        format!("{readout_ms:.3}\n").as_bytes(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The readout a frontend saved is what the merger records in a saved map, and what a
    /// restarted frontend resumes with; a damaged or impossible value is not used.
    #[test]
    fn a_saved_readout_is_read_back_and_a_bad_one_ignored() {
        let out = tempfile::tempdir().expect("tempdir");
        assert_eq!(read(out.path()), None);
        write(out.path(), 21.5).expect("saved");
        assert_eq!(read(out.path()), Some(21.5));
        for bad in ["", "fast", "-3", "500", "NaN"] {
            std::fs::write(crate::state_dir(out.path()).join(FILE_NAME), bad).expect("written");
            assert_eq!(read(out.path()), None, "{bad}");
        }
    }
}
