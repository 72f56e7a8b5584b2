//! What the machine gives this process (memory, file descriptors), from which the server's
//! default limits derive, so that a limit is reached with an error answer before the kernel or
//! the allocator stops the process.

use std::io;

/// The soft limit of an rlimit, `None` when unlimited or unreadable. A macro because the type of
/// the resource argument differs between C libraries.
macro_rules! soft_limit {
    ($resource:ident) => {{
        let mut limit = libc::rlimit {
            rlim_cur: 0,
            rlim_max: 0,
        };
        // SAFETY: getrlimit writes one rlimit through a valid pointer.
        let read = unsafe { libc::getrlimit(libc::$resource, &mut limit) } == 0;
        (read && limit.rlim_cur != libc::RLIM_INFINITY).then_some(limit.rlim_cur)
    }};
}

/// Bytes of memory this process can use: the least of the machine's memory, its cgroup's limit
/// and its address-space and data-segment rlimits; `None` when none of them can be read.
pub fn memory_limit() -> Option<u64> {
    [
        physical_memory(),
        cgroup_memory_limit(),
        soft_limit!(RLIMIT_AS),
        soft_limit!(RLIMIT_DATA),
    ]
    .into_iter()
    .flatten()
    .min()
}

/// The default session memory budget (`--max-session-memory`): half of [`memory_limit`], leaving
/// the other half to requests in flight, connections and the allocator's slack; 1 GiB when the
/// limit cannot be read.
pub fn default_session_memory() -> usize {
    memory_limit().map_or(1 << 30, |bytes| {
        usize::try_from(bytes / 2).unwrap_or(usize::MAX)
    })
}

/// File descriptors kept for everything but client connections: stdio, listeners, the runtime's
/// own, Zenoh's sockets and the metrics endpoint.
const RESERVED_FILES: u64 = 64;

/// Most connections held by default, whatever the file limit: each costs tens of KiB.
const MAX_DEFAULT_CONNECTIONS: u64 = 4096;

/// The default connection limit (`--max-connections`): what the open-files limit allows after
/// [`RESERVED_FILES`], between 16 and [`MAX_DEFAULT_CONNECTIONS`].
pub fn default_max_connections() -> usize {
    let files = soft_limit!(RLIMIT_NOFILE).unwrap_or(MAX_DEFAULT_CONNECTIONS);
    let connections = files
        .saturating_sub(RESERVED_FILES)
        .clamp(16, MAX_DEFAULT_CONNECTIONS);
    usize::try_from(connections).unwrap_or(usize::MAX)
}

/// Raises the soft limit on open files to the hard limit (the soft one is often 1,024 while the
/// hard one allows far more) and returns the soft limit now in effect.
pub fn raise_open_files_limit() -> io::Result<u64> {
    let mut limit = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit and setrlimit read and write one rlimit through a valid pointer.
    if unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit) } != 0 {
        return Err(io::Error::last_os_error());
    }
    if limit.rlim_cur < limit.rlim_max {
        let raised = libc::rlimit {
            rlim_cur: limit.rlim_max,
            rlim_max: limit.rlim_max,
        };
        // SAFETY: as above.
        if unsafe { libc::setrlimit(libc::RLIMIT_NOFILE, &raised) } != 0 {
            return Err(io::Error::last_os_error());
        }
        limit = raised;
    }
    Ok(limit.rlim_cur)
}

fn physical_memory() -> Option<u64> {
    // SAFETY: sysconf only reads system configuration.
    let (pages, page_size) = unsafe {
        (
            libc::sysconf(libc::_SC_PHYS_PAGES),
            libc::sysconf(libc::_SC_PAGESIZE),
        )
    };
    let pages = u64::try_from(pages).ok()?;
    let page_size = u64::try_from(page_size).ok()?;
    pages.checked_mul(page_size)
}

/// The memory limit of this process's cgroup (v2, else v1); `None` when there is none.
fn cgroup_memory_limit() -> Option<u64> {
    let cgroups = std::fs::read_to_string("/proc/self/cgroup").ok()?;
    let unified = cgroups.lines().find_map(|line| line.strip_prefix("0::"));
    let candidates = [
        unified.map(|path| format!("/sys/fs/cgroup{}/memory.max", path.trim_end_matches('/'))),
        Some("/sys/fs/cgroup/memory.max".to_string()),
        Some("/sys/fs/cgroup/memory/memory.limit_in_bytes".to_string()),
    ];
    candidates
        .into_iter()
        .flatten()
        .find_map(|path| std::fs::read_to_string(path).ok())
        // "max" (v2) does not parse; v1 reports no limit as a number near 2^63.
        .and_then(|text| text.trim().parse::<u64>().ok())
        .filter(|&bytes| bytes < 1 << 62)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_defaults_fit_what_the_machine_has() {
        let limit = memory_limit().expect("this machine's memory");
        assert!(limit >= 1 << 20, "{limit}");
        assert_eq!(default_session_memory() as u64, limit / 2);
        let connections = default_max_connections() as u64;
        assert!((16..=MAX_DEFAULT_CONNECTIONS).contains(&connections));
        if let Some(files) = soft_limit!(RLIMIT_NOFILE) {
            assert!(connections <= files.saturating_sub(RESERVED_FILES).max(16));
        }
    }
}
