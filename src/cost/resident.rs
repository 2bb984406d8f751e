//! How much the process has grown during one script evaluation, read from the operating
//! system: Rhai counts the data limits of an assignment's item only, not of the array or map
//! it goes into, so `for i in 0..99990 { a[i] = s; }` with a 99,990-element `s` held 3.2 GB
//! in the 5 s before the wall time stopped it (16 GB on a machine twice as fast), each item
//! within every limit Rhai checks.

use std::cell::Cell;
use std::time::{Duration, Instant};

/// An evaluation younger than this is not measured: most finish in well under a millisecond,
/// and reading the operating system's figure costs about 10 µs.
const FIRST: Duration = Duration::from_millis(5);
/// Between two readings.
const EVERY: Duration = Duration::from_millis(5);

/// Resident bytes of the process, where the operating system says (Linux); `None` elsewhere.
pub(crate) fn resident_bytes() -> Option<usize> {
    #[cfg(target_os = "linux")]
    {
        let statm = std::fs::read_to_string("/proc/self/statm").ok()?;
        let pages: usize = statm.split_whitespace().nth(1)?.parse().ok()?;
        // SAFETY: sysconf only reads a system constant.
        let page = unsafe { libc::sysconf(libc::_SC_PAGESIZE) };
        usize::try_from(page).ok().map(|p| pages.saturating_mul(p))
    }
    #[cfg(not(target_os = "linux"))]
    {
        None
    }
}

/// Watches one engine's evaluations for growth of the process past a limit.
#[derive(Default)]
pub(crate) struct GrowthWatch {
    /// The operations counted when last looked at (a smaller count is a new evaluation), the
    /// resident bytes when the evaluation was first measured, and when they were last read.
    state: Cell<Option<(u64, usize, Instant)>>,
}

impl GrowthWatch {
    /// Whether the process has grown by more than `limit` bytes since this evaluation (begun
    /// at `started`, `ops` operations in) was first measured.
    pub(crate) fn over(&self, started: Instant, ops: u64, limit: usize) -> bool {
        let now = Instant::now();
        if now.duration_since(started) < FIRST {
            return false;
        }
        match self.state.get() {
            Some((seen, base, last)) if seen <= ops => {
                if now.duration_since(last) < EVERY {
                    self.state.set(Some((ops, base, last)));
                    return false;
                }
                self.state.set(Some((ops, base, now)));
                resident_bytes().is_some_and(|r| r.saturating_sub(base) > limit)
            }
            _ => {
                self.state.set(resident_bytes().map(|r| (ops, r, now)));
                false
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg(target_os = "linux")]
    #[test]
    fn growth_is_measured_from_an_evaluation_s_first_reading() {
        let w = GrowthWatch::default();
        let started = Instant::now() - Duration::from_secs(1);
        assert!(
            !w.over(started, 512, 64 << 20),
            "the first reading is the baseline"
        );
        let held: Vec<u8> = vec![1; 256 << 20];
        std::thread::sleep(EVERY);
        assert!(w.over(started, 1024, 64 << 20), "256 MB written since");
        assert!(held.iter().all(|b| *b == 1));
        // A new evaluation (fewer operations) measures from its own first reading.
        assert!(!w.over(started, 512, 64 << 20));
        std::thread::sleep(EVERY);
        assert!(!w.over(started, 1024, 64 << 20));
        assert!(resident_bytes().is_some());
    }
}
