//! Handing freed heap memory back to the system. glibc's allocator keeps what a process
//! freed for its next allocations, so a process that once held a large transient working
//! set (the launcher's calibration pre-passes, which track and solve hundreds of frames
//! before the services start; the checkpoint's serialization buffer and a folded
//! background refinement in the merger) keeps it resident for the rest of the run, and a
//! wearable's memory budget counts it. `malloc_trim` returns the free pages at the top of
//! the heap and, since glibc 2.8, the whole free pages inside it (madvise).

/// Returns the process's free heap pages to the system; the resident bytes it saved, by
/// the process's own count (0 where it cannot tell, or off glibc, where it does nothing).
pub fn return_freed_memory() -> u64 {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        let before = resident_bytes();
        // SAFETY: malloc_trim only walks the allocator's own free lists; it takes no
        // pointers and is safe to call at any time from any thread.
        unsafe { libc::malloc_trim(0) };
        before.saturating_sub(resident_bytes())
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    {
        0
    }
}

/// This process's resident set in bytes (`/proc/self/statm`), 0 when unreadable.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn resident_bytes() -> u64 {
    let pages = std::fs::read_to_string("/proc/self/statm")
        .ok()
        .and_then(|s| s.split_whitespace().nth(1)?.parse::<u64>().ok())
        .unwrap_or(0);
    // SAFETY: sysconf reads a constant of the system.
    let page = unsafe { libc::sysconf(libc::_SC_PAGESIZE) };
    pages * u64::try_from(page).unwrap_or(4096)
}

#[cfg(all(test, target_os = "linux", target_env = "gnu"))]
mod tests {
    use super::*;

    /// Set in the child process that measures alone.
    const CHILD: &str = "EGOSLAM_MEMORY_TEST_CHILD";

    #[test]
    fn a_freed_working_set_leaves_the_resident_set() {
        if std::env::var_os(CHILD).is_none() {
            // The resident set is the whole process's, and the other tests allocate
            // meanwhile: measured in a child running this test alone.
            let status = std::process::Command::new(std::env::current_exe().expect("test binary"))
                .args([
                    "--exact",
                    "memory::tests::a_freed_working_set_leaves_the_resident_set",
                    "--test-threads=1",
                ])
                .env(CHILD, "1")
                .status()
                .expect("child test");
            assert!(status.success(), "the child's measurement failed");
            return;
        }
        // 64 MiB in small blocks (below the mmap threshold, so they come from the heap and
        // stay with the allocator once freed), touched so that they are resident.
        let blocks: Vec<Vec<u8>> = (0..4096).map(|_| vec![1u8; 16 * 1024]).collect();
        let held = resident_bytes();
        drop(blocks);
        let saved = return_freed_memory();
        assert!(
            saved > 32 << 20,
            "returned {saved} bytes of a 64 MiB working set (resident {held} while held)"
        );
    }
}
