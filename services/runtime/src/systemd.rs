//! systemd integration without libsystemd: `sd_notify` datagrams to `$NOTIFY_SOCKET`
//! (READY, STATUS, STOPPING, WATCHDOG) and the watchdog thread. Outside systemd (no
//! `NOTIFY_SOCKET`) everything here does nothing.
//!
//! The watchdog pings only while the service shows signs of life: its main loop and the
//! bus's waiting loops record activity (`egoslam_bus::last_activity`); a main thread stuck
//! for longer than half of `WatchdogSec` stops the pings and systemd restarts the unit.

use std::os::unix::net::UnixDatagram;
use std::time::Duration;

/// Sends one notification (e.g. "READY=1"); silently nothing outside systemd.
pub fn notify(state: &str) {
    let Some(path) = std::env::var_os("NOTIFY_SOCKET") else {
        return;
    };
    let Ok(socket) = UnixDatagram::unbound() else {
        return;
    };
    let bytes = path.as_encoded_bytes();
    let sent = if let Some(name) = bytes.strip_prefix(b"@") {
        use std::os::linux::net::SocketAddrExt;
        std::os::unix::net::SocketAddr::from_abstract_name(name)
            .and_then(|addr| socket.send_to_addr(state.as_bytes(), &addr))
    } else {
        socket.send_to(state.as_bytes(), &path)
    };
    if let Err(e) = sent {
        tracing::warn!(error = %e, "sd_notify failed");
    }
}

/// The watchdog interval systemd asked for (`WATCHDOG_USEC`), if any.
fn watchdog_interval() -> Option<Duration> {
    let usec: u64 = std::env::var("WATCHDOG_USEC").ok()?.parse().ok()?;
    (usec > 0).then(|| Duration::from_micros(usec))
}

/// Tells systemd the service is ready and starts the watchdog pings (if enabled).
pub fn ready(service: &str) {
    notify(&format!("READY=1\nSTATUS={service} running"));
    let Some(interval) = watchdog_interval() else {
        return;
    };
    let spawned = std::thread::Builder::new()
        .name("watchdog".into())
        .spawn(move || loop {
            std::thread::sleep(interval / 4);
            if egoslam_bus::last_activity().elapsed() < interval / 2 {
                notify("WATCHDOG=1");
            }
        });
    if let Err(e) = spawned {
        tracing::warn!(error = %e, "no watchdog thread");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn notifications_reach_the_socket() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("notify");
        let listener = UnixDatagram::bind(&path).expect("bind");
        // SAFETY: single-threaded test body; no other thread reads the environment now.
        unsafe { std::env::set_var("NOTIFY_SOCKET", &path) };
        notify("READY=1");
        unsafe { std::env::remove_var("NOTIFY_SOCKET") };
        let mut buf = [0u8; 64];
        let n = listener.recv(&mut buf).expect("received");
        assert_eq!(&buf[..n], b"READY=1");
    }
}
