//! Data parallelism shared by the stages: independent jobs on a few threads (perception's clouds,
//! the blocks of one SVI iteration and their Laplace steps, criticism's candidate effects).
//!
//! Results come back in job order and are combined by the caller in that order, so a result is
//! bit-identical for every thread count (floating-point sums are not reordered).

use std::sync::atomic::{AtomicIsize, AtomicUsize, Ordering};

/// The number of threads for `requested` (0: every core the process may use, as
/// [`std::thread::available_parallelism`] reports; 1 when that is unknown).
pub fn resolve_threads(requested: usize) -> usize {
    if requested > 0 {
        requested
    } else {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    }
}

/// `(0..jobs).map(f)` on up to `threads` threads, the calling one included; the results in job
/// order. Jobs are handed out one at a time (their costs differ: a rigid block has no physics).
/// A panic in any job resumes on the calling thread.
pub fn map<R: Send>(threads: usize, jobs: usize, f: impl Fn(usize) -> R + Sync) -> Vec<R> {
    let threads = threads.min(jobs).max(1);
    if threads == 1 {
        return (0..jobs).map(f).collect();
    }
    let next = AtomicUsize::new(0);
    let work = || {
        let mut out = Vec::new();
        loop {
            let j = next.fetch_add(1, Ordering::Relaxed);
            if j >= jobs {
                break out;
            }
            out.push((j, f(j)));
        }
    };
    let mut done: Vec<(usize, R)> = std::thread::scope(|s| {
        let others: Vec<_> = (1..threads).map(|_| s.spawn(work)).collect();
        let mut done = work();
        for h in others {
            done.extend(h.join().unwrap_or_else(|e| std::panic::resume_unwind(e)));
        }
        done
    });
    done.sort_unstable_by_key(|(j, _)| *j);
    done.into_iter().map(|(_, r)| r).collect()
}

/// Cores shared by concurrent work of one SVI fit (the starts of [`crate::inference::svi::fit`]):
/// each piece of parallel work borrows the spare ones for its duration, and a start that finishes
/// gives its own core to the others. Which thread runs a job never changes a result ([`map`]).
#[derive(Debug)]
pub struct Cores {
    /// Cores free for borrowing; negative while the callers' threads outnumber the cores.
    spare: AtomicIsize,
}

impl Cores {
    /// `total` cores of which `busy` are taken by the callers' own threads (more than `total`:
    /// none is spare until enough of them have given theirs back).
    pub fn new(total: usize, busy: usize) -> Self {
        Cores { spare: AtomicIsize::new(total as isize - busy as isize) }
    }

    /// [`map`] on the calling thread plus as many spare cores as are free now (at most
    /// `jobs - 1`); they are given back when it returns.
    pub fn map<R: Send>(&self, jobs: usize, f: impl Fn(usize) -> R + Sync) -> Vec<R> {
        let want = jobs.saturating_sub(1) as isize;
        let take = |s: isize| s.clamp(0, want);
        let extra = self.spare.fetch_update(Ordering::AcqRel, Ordering::Acquire, |s| Some(s - take(s))).map_or(0, take);
        let out = map(1 + extra as usize, jobs, f);
        self.give(extra as usize);
        out
    }

    /// Returns `n` cores (a caller's thread that has finished its work).
    pub fn give(&self, n: usize) {
        self.spare.fetch_add(n as isize, Ordering::AcqRel);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn results_come_back_in_job_order_for_every_thread_count() {
        let serial: Vec<u64> = (0..37).map(|j| (j as u64).pow(3) % 11).collect();
        for threads in [1, 2, 3, 8, 64] {
            assert_eq!(map(threads, 37, |j| (j as u64).pow(3) % 11), serial, "{threads} threads");
        }
        assert!(map(4, 0, |j| j).is_empty());
        let cores = Cores::new(3, 1);
        assert_eq!(cores.map(37, |j| (j as u64).pow(3) % 11), serial);
        assert_eq!(cores.spare.load(Ordering::Acquire), 2, "borrowed cores are given back");
        let cores = Cores::new(1, 2);
        assert_eq!(cores.map(5, |j| j), vec![0, 1, 2, 3, 4]);
        cores.give(1);
        assert_eq!(cores.spare.load(Ordering::Acquire), 0, "one core, two callers: none spare after one finishes");
    }

    #[test]
    fn a_panicking_job_resumes_on_the_caller() {
        let r = std::panic::catch_unwind(|| map(2, 8, |j| if j == 5 { panic!("job 5") } else { j }));
        assert!(r.is_err());
    }
}
