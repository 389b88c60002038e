//! [`Progress`]: the fraction of a long job done, which the CLI's progress
//! bars read. The builders, loading, the slim pass and rendering advance
//! one; it lives outside [`crate::build`] so that those stages need not
//! know the builder.

use std::sync::atomic::{AtomicU64, Ordering};

/// The progress of a long job, for a progress bar: a fraction from 0 to 1
/// that other threads may read while the job runs.
///
/// In a build, each node carries a weight; the root's is
/// [`Progress::TOTAL`] and a split shares a node's weight between its
/// children in proportion to their triangle counts. A leaf adds its
/// weight, so the sum reaches `TOTAL` exactly when the build ends. The
/// slim pass ([`crate::slim::slim_with_progress`]) shares weights the same
/// way over subtrees; loading an OBJ file counts bytes read and rendering
/// counts tiles ([`Progress::advance`]).
#[derive(Debug, Default)]
pub struct Progress {
    done: AtomicU64,
}

impl Progress {
    /// The weight of a whole job.
    pub const TOTAL: u64 = 1 << 40;

    /// The fraction done, from 0 to 1.
    pub fn fraction(&self) -> f64 {
        self.done.load(Ordering::Relaxed) as f64 / Self::TOTAL as f64
    }

    pub(crate) fn add(progress: Option<&Progress>, weight: u64) {
        if let Some(p) = progress {
            p.done.fetch_add(weight, Ordering::Relaxed);
        }
    }

    /// Marks the whole job done (for one that finishes at once).
    pub fn add_all(progress: Option<&Progress>) {
        Progress::add(progress, Self::TOTAL);
    }

    /// Adds the share of the work between `before` and `after` units of
    /// `whole` (which must not be 0). Shares of consecutive ranges sum to
    /// exactly `TOTAL` over `0..whole`, with no rounding lost.
    pub fn advance(progress: Option<&Progress>, before: u64, after: u64, whole: u64) {
        let at =
            |units: u64| (u128::from(Self::TOTAL) * u128::from(units) / u128::from(whole)) as u64;
        Progress::add(progress, at(after) - at(before));
    }

    /// Shares `weight` between children of `n_left` and `n_right` triangles.
    pub(crate) fn share(weight: u64, n_left: usize, n_right: usize) -> (u64, u64) {
        let total = (n_left + n_right).max(1) as u128;
        let left = (weight as u128 * n_left as u128 / total) as u64;
        (left, weight - left)
    }
}
