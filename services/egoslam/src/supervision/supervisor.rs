//! Supervision of the services `egoslam run` starts: restarts after a crash, and a stop on
//! SIGINT/SIGTERM that keeps what was processed.
//!
//! The services run in their own process group, so a Ctrl-C on the terminal reaches the
//! launcher alone, which stops them in order: the replay first (it stops reading and ends
//! the stream), so that the frontend, solver and merger finish what was sent and write their
//! results; whatever still runs [`DRAIN`] after the signal gets SIGTERM (and exits within
//! its own grace, `egoslam_bus::STOP_GRACE`), and whatever runs [`KILL_AFTER`] after it is
//! killed. A second signal kills every service at once.

use anyhow::{bail, Context};
use std::process::{Child, Command};
use std::sync::atomic::{AtomicBool, AtomicI32, AtomicUsize, Ordering};
use std::time::{Duration, Instant};

/// Services the supervisor restarts when they die by a signal: the merger resumes exactly
/// (checkpoint + journal); a restarted frontend continues its ids and a restarted solver
/// starts a new stream, which the merger continues as a new map segment (the keyframes in
/// flight are lost: docs/durability.md). The replay (camera) is not restarted.
const RESTARTABLE: &[&str] = &["merger", "solver", "frontend"];

/// Restarts allowed per service within [`RESTART_INTERVAL`] (as systemd's StartLimitBurst
/// and StartLimitIntervalSec): a service that keeps dying has a real problem, but one killed
/// now and then on a long run is restarted every time.
const RESTART_BURST: usize = 3;
const RESTART_INTERVAL: Duration = Duration::from_secs(60);

pub struct Supervised {
    name: &'static str,
    args: Vec<String>,
    child: Child,
    restarts: u32,
    /// When the restarts within the last [`RESTART_INTERVAL`] happened.
    recent_restarts: std::collections::VecDeque<Instant>,
}

impl Supervised {
    /// Whether one more restart stays within the burst limit (forgets older restarts).
    fn may_restart(&mut self, now: Instant) -> bool {
        while self
            .recent_restarts
            .front()
            .is_some_and(|t| now.duration_since(*t) > RESTART_INTERVAL)
        {
            self.recent_restarts.pop_front();
        }
        self.recent_restarts.len() < RESTART_BURST
    }
}

pub fn spawn(name: &'static str, args: &[String]) -> anyhow::Result<Supervised> {
    let exe = std::env::current_exe().context("locating the egoslam executable")?;
    let lean = lean_service_binary(&exe, name);
    let started = match &lean {
        Some(lean) => start_service(lean, None, args).or_else(|e| {
            // A lean binary that does not start (removed or made unrunnable since it was
            // checked) must not stop the run: the multi-call binary has the same service.
            tracing::warn!(binary = %lean.display(), error = %e, "lean service binary did not start; running `egoslam {name}`");
            start_service(&exe, Some(name), args)
        }),
        None => {
            if LEAN_SERVICES.contains(&name) && !TOLD_NO_LEAN_BINARIES.swap(true, Ordering::Relaxed)
            {
                tracing::info!(
                    "the services run as `egoslam SERVICE` (no egoslam-{name} of this build next to egoslam; `cargo build -p egoslam` builds them), which loads ~250 shared libraries at each start"
                );
            }
            start_service(&exe, Some(name), args)
        }
    };
    let child = started.with_context(|| format!("starting the {name} service"))?;
    Ok(Supervised {
        name,
        args: args.to_vec(),
        child,
        restarts: 0,
        recent_restarts: Default::default(),
    })
}

/// Starts `program` (with the subcommand `subcommand`, for the multi-call binary) and
/// `args` as a service process.
fn start_service(
    program: &std::path::Path,
    subcommand: Option<&str>,
    args: &[String],
) -> std::io::Result<Child> {
    use std::os::unix::process::CommandExt;
    let mut command = Command::new(program);
    command.args(subcommand).args(args);
    // A launcher that is killed (SIGKILL, or SIGTERM, which it does not catch) must not
    // leave its services running on: each gets SIGTERM when the launcher dies, and stops
    // as on any SIGTERM. Found when two killed runs kept writing into one output folder.
    // SAFETY: prctl is async-signal-safe and touches no memory of the parent.
    unsafe {
        command.pre_exec(|| {
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            // Its own process group: a terminal's Ctrl-C reaches the launcher only, which
            // stops the services in order (module documentation).
            if libc::setpgid(0, 0) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    command.spawn()
}

/// The services built as lean binaries of their own (src/bin/).
const LEAN_SERVICES: &[&str] = &["frontend", "solver", "merger"];

/// Whether the launcher has said that it runs the services without their lean binaries.
static TOLD_NO_LEAN_BINARIES: AtomicBool = AtomicBool::new(false);

/// How much older than the running `egoslam` a lean service binary next to it may be and
/// still count as built with it: cargo links a package's binaries one after another, in
/// no set order, within seconds.
const SAME_BUILD_SLACK: Duration = Duration::from_secs(120);

/// The lean binary of service `name` (`egoslam-NAME`, lib.rs) next to `exe`, when there is
/// one from the same build: it starts in milliseconds where the multi-call binary loads
/// ~250 shared libraries (video and image decoding) first. One older than `exe` (a build
/// of `egoslam` alone, which leaves its siblings as they were) could speak an older
/// protocol, so `exe` runs the service itself then.
fn lean_service_binary(exe: &std::path::Path, name: &str) -> Option<std::path::PathBuf> {
    use std::io::Read;
    use std::os::unix::fs::PermissionsExt;
    let lean = exe.with_file_name(egoslam_runtime::process_role::lean_binary_name(name));
    let own = std::fs::metadata(exe).and_then(|m| m.modified()).ok()?;
    let metadata = std::fs::metadata(&lean).ok()?;
    let theirs = metadata.modified().ok()?;
    // An executable ELF file: anything else (a file cut short, a script) would start as a
    // shell's "not found" rather than fail to start.
    let executable = metadata.permissions().mode() & 0o111 != 0;
    let mut magic = [0u8; 4];
    let elf = std::fs::File::open(&lean)
        .and_then(|mut f| f.read_exact(&mut magic))
        .is_ok()
        && magic == *b"\x7fELF";
    (executable && elf && theirs + SAME_BUILD_SLACK >= own).then_some(lean)
}

pub fn stop_all(children: &mut [Supervised]) {
    stop_all_within(children, Duration::from_secs(3));
}

/// [`stop_all`], killing what still runs after `grace`.
fn stop_all_within(children: &mut [Supervised], grace: Duration) {
    // SIGTERM first: services finish their current item and release shared memory. Only
    // to those still running: a service that has exited was reaped by `try_wait`, its
    // process id may already be another process's.
    children.iter_mut().for_each(|c| signal(c, libc::SIGTERM));
    let deadline = Instant::now() + grace;
    for c in children.iter_mut() {
        while Instant::now() < deadline && matches!(c.child.try_wait(), Ok(None)) {
            std::thread::sleep(Duration::from_millis(20));
        }
        let _ = c.child.kill();
        let _ = c.child.wait();
    }
}

/// How long the services of a round started again have to stop before they are killed.
const RESTART_GRACE: Duration = Duration::from_millis(300);

/// After a stop request, how long the services have to finish what was sent before the
/// ones still running get SIGTERM.
pub const DRAIN: Duration = Duration::from_millis(2500);
/// After a stop request, when every service still running is killed: the launcher is done
/// within 5 s of the signal, report included.
pub const KILL_AFTER: Duration = Duration::from_millis(4600);

/// Stop requests (SIGINT, SIGTERM) received by the launcher, and the last signal's number.
static STOP_REQUESTS: AtomicUsize = AtomicUsize::new(0);
static STOP_SIGNAL: AtomicI32 = AtomicI32::new(0);

/// Counts SIGINT and SIGTERM from now on instead of dying by them (call before starting the
/// services).
pub fn catch_stop_signals() -> anyhow::Result<()> {
    for signal in [libc::SIGINT, libc::SIGTERM] {
        // SAFETY: the action only does atomic stores, which are async-signal-safe.
        unsafe {
            signal_hook::low_level::register(signal, move || {
                STOP_SIGNAL.store(signal, Ordering::Relaxed);
                STOP_REQUESTS.fetch_add(1, Ordering::Relaxed);
            })
        }
        .with_context(|| format!("catching signal {signal}"))?;
    }
    Ok(())
}

/// How a supervised run ended.
#[derive(Debug)]
pub struct Supervision {
    /// Restarts per service.
    pub restarts: Vec<(&'static str, u32)>,
    /// The signal that stopped the run early, if one did.
    pub interrupted_by: Option<i32>,
    /// The services were stopped to start the run again (`start_again` said so).
    pub started_again: bool,
}

fn signal(c: &mut Supervised, signal: i32) {
    if matches!(c.child.try_wait(), Ok(None)) {
        if let Ok(pid) = libc::pid_t::try_from(c.child.id()) {
            // SAFETY: kill(2) touches no memory; `pid` is our unreaped child.
            unsafe { libc::kill(pid, signal) };
        }
    }
}

/// Waits for every service. A restartable service killed by a signal (SIGKILL, a crash) is
/// started again; any other failure stops the others and is reported. A stop request stops
/// them as the module documentation says. `start_again` is asked every round while no
/// stop was requested: when it says so, every service is stopped at once (the run starts
/// again: stream_calibration.rs).
pub fn supervise(
    mut children: Vec<Supervised>,
    mut start_again: impl FnMut() -> bool,
) -> anyhow::Result<Supervision> {
    use std::os::unix::process::ExitStatusExt;
    let mut stop_started: Option<Instant> = None;
    let mut terminated = false;
    loop {
        if stop_started.is_none() && STOP_REQUESTS.load(Ordering::Relaxed) == 0 && start_again() {
            // Nothing of theirs is kept: a service still finishing an item (a send to a
            // consumer that has gone waits out its 2 s grace) is killed; the next round's
            // services clean up the dead nodes' bus resources when they open the bus.
            stop_all_within(&mut children, RESTART_GRACE);
            return Ok(Supervision {
                restarts: children.iter().map(|c| (c.name, c.restarts)).collect(),
                interrupted_by: None,
                started_again: true,
            });
        }
        let requests = STOP_REQUESTS.load(Ordering::Relaxed);
        if requests >= 2 {
            tracing::warn!("second stop request: killing every service");
            for c in children.iter_mut() {
                let _ = c.child.kill();
                let _ = c.child.wait();
            }
            std::process::exit(128 + STOP_SIGNAL.load(Ordering::Relaxed));
        }
        if requests == 1 && stop_started.is_none() {
            tracing::warn!("stop requested: ending the stream; a second Ctrl-C stops at once");
            stop_started = Some(Instant::now());
            for c in children.iter_mut().filter(|c| c.name == "replay") {
                signal(c, libc::SIGTERM);
            }
        }
        if let Some(t) = stop_started {
            if !terminated && t.elapsed() > DRAIN {
                terminated = true;
                tracing::warn!(
                    "services still finishing {:.1} s after the stop request: SIGTERM",
                    DRAIN.as_secs_f64()
                );
                children.iter_mut().for_each(|c| signal(c, libc::SIGTERM));
            }
            if t.elapsed() > KILL_AFTER {
                for c in children.iter_mut() {
                    if matches!(c.child.try_wait(), Ok(None)) {
                        tracing::error!(service = c.name, "killed: did not stop in time");
                        let _ = c.child.kill();
                    }
                }
            }
        }
        let mut running = 0;
        for i in 0..children.len() {
            match children[i].child.try_wait()? {
                None => running += 1,
                // Stopping: whatever ends, ends (nothing is restarted or reported failed).
                Some(_) if stop_started.is_some() => {}
                Some(status)
                    if status.signal().is_some()
                        && RESTARTABLE.contains(&children[i].name)
                        && children[i].may_restart(Instant::now()) =>
                {
                    let c = &mut children[i];
                    tracing::warn!(service = c.name, %status, "service died; restarting it");
                    let again = spawn(c.name, &c.args)?;
                    c.child = again.child;
                    c.restarts += 1;
                    c.recent_restarts.push_back(Instant::now());
                    running += 1;
                }
                Some(status) if !status.success() => {
                    let name = children[i].name;
                    stop_all(&mut children);
                    bail!("the {name} service failed ({status}); the pipeline was stopped");
                }
                Some(_) => {}
            }
        }
        if running == 0 {
            return Ok(Supervision {
                restarts: children.iter().map(|c| (c.name, c.restarts)).collect(),
                interrupted_by: stop_started.map(|_| STOP_SIGNAL.load(Ordering::Relaxed)),
                started_again: false,
            });
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_binary_that_cannot_start_is_an_error_to_fall_back_on() {
        // Not executable: exec fails (spawn then starts the multi-call binary), while a
        // program with a subcommand starts.
        let dir = tempfile::tempdir().expect("tempdir");
        let broken = dir.path().join("egoslam-solver");
        std::fs::write(&broken, "not a program").expect("write");
        assert!(start_service(&broken, None, &[]).is_err());
        let mut child =
            start_service(std::path::Path::new("true"), Some("solver"), &[]).expect("true");
        assert!(child.wait().expect("wait").success());
    }

    #[test]
    fn a_lean_service_binary_is_used_only_from_the_same_build() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().expect("tempdir");
        let exe = dir.path().join("egoslam");
        let lean = dir.path().join("egoslam-solver");
        // A file with an ELF header, executable, modified `age` ago.
        let touch = |path: &std::path::Path, age: Duration| {
            std::fs::write(path, b"\x7fELF\x02\x01\x01").expect("write");
            let file = std::fs::File::options()
                .write(true)
                .open(path)
                .expect("open");
            file.set_modified(std::time::SystemTime::now() - age)
                .expect("set mtime");
            std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o755)).expect("chmod");
        };
        touch(&exe, Duration::ZERO);
        assert_eq!(lean_service_binary(&exe, "solver"), None, "none there");
        touch(&lean, Duration::from_secs(30));
        assert_eq!(
            lean_service_binary(&exe, "solver"),
            Some(lean.clone()),
            "same build"
        );
        assert_eq!(
            lean_service_binary(&exe, "merger"),
            None,
            "another service's"
        );
        touch(&lean, Duration::from_secs(3600));
        assert_eq!(
            lean_service_binary(&exe, "solver"),
            None,
            "left by an older build"
        );
        touch(&lean, Duration::ZERO);
        std::fs::write(&lean, "#!/bin/sh\n").expect("script");
        assert_eq!(lean_service_binary(&exe, "solver"), None, "not an ELF file");
        touch(&lean, Duration::ZERO);
        std::fs::set_permissions(&lean, std::fs::Permissions::from_mode(0o644)).expect("chmod");
        assert_eq!(lean_service_binary(&exe, "solver"), None, "not executable");
    }

    #[test]
    fn restarts_are_limited_per_interval_not_per_run() {
        let child = Command::new("true").spawn().expect("spawn true");
        let mut s = Supervised {
            name: "solver",
            args: Vec::new(),
            child,
            restarts: 0,
            recent_restarts: Default::default(),
        };
        let t0 = Instant::now();
        for k in 0..RESTART_BURST {
            assert!(s.may_restart(t0 + Duration::from_secs(k as u64)));
            s.recent_restarts
                .push_back(t0 + Duration::from_secs(k as u64));
        }
        assert!(!s.may_restart(t0 + Duration::from_secs(10)), "burst spent");
        // A minute after the first restart, one more is allowed; a kill every 60 s never
        // runs out.
        assert!(s.may_restart(t0 + RESTART_INTERVAL + Duration::from_secs(1)));
        let _ = s.child.wait();
    }
}
