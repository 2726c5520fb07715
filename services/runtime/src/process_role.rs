//! Which egoslam process a command line belongs to: `egoslam ROLE ...` (the multi-call
//! binary: `run`, `replay`, or a service) or `egoslam-SERVICE ...` (a service's lean
//! binary, which `egoslam run` starts when it lies next to it). The launcher names the
//! lean binaries with [`lean_binary_name`]; the endurance benchmark and the tests find a
//! run's processes with [`role`].

/// The file name of `service`'s lean binary.
pub fn lean_binary_name(service: &str) -> String {
    format!("egoslam-{service}")
}

/// The role of the process whose `/proc/PID/cmdline` is `cmdline` (arguments separated by
/// NUL bytes): the lean binary's service, else the first argument; empty when there is
/// none.
pub fn role(cmdline: &[u8]) -> &[u8] {
    let mut args = cmdline.split(|b| *b == 0);
    let program = args.next().unwrap_or_default();
    let name = program.rsplit(|b| *b == b'/').next().unwrap_or_default();
    match name.strip_prefix(lean_binary_name("").as_bytes()) {
        Some(lean) if !lean.is_empty() => lean,
        _ => args.next().unwrap_or_default(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_process_is_known_by_its_subcommand_or_its_lean_binary() {
        assert_eq!(role(b"/usr/bin/egoslam\0run\0--input\0x\0"), b"run");
        assert_eq!(role(b"target/egoslam\0merger\0--out=o\0"), b"merger");
        assert_eq!(role(b"/opt/egoslam-frontend\0--out=o\0"), b"frontend");
        assert_eq!(role(b"egoslam-solver\0"), b"solver");
        assert_eq!(role(b""), b"");
        assert_eq!(lean_binary_name("solver"), "egoslam-solver");
    }
}
