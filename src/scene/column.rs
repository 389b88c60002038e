//! The storage of one column of [`super::TriangleColumns`]: a vector the
//! loader filled, or a window of a read-only file mapping (a `.kds` scene
//! cache), so that a cached scene's columns are file-backed pages the
//! kernel can drop and read again, not anonymous memory.
//!
//! Either way the column reads as a plain `&[T]`; a mapped column is
//! copied into a vector only when it is changed ([`Column::to_mut`]).

use std::fmt;
use std::ops::Deref;
use std::sync::Arc;

/// A column of `T`: owned, or `len` values at byte `start` of a shared map.
pub(crate) enum Column<T: 'static> {
    /// Values in anonymous memory.
    Owned(Vec<T>),
    /// Values in a mapping: `values` lies inside `map`, which this column
    /// keeps alive (so the slice is valid as long as the column is, though
    /// its lifetime says `'static`; it is only ever handed out borrowed
    /// from `&self`).
    Mapped {
        map: Arc<memmap2::Mmap>,
        values: &'static [T],
    },
}

impl<T: bytemuck::Pod> Column<T> {
    /// `len` values at byte `start` of `map`, or `None` if they do not lie
    /// inside it or are not aligned for `T`.
    pub(crate) fn mapped(map: Arc<memmap2::Mmap>, start: usize, len: usize) -> Option<Column<T>> {
        let end = len
            .checked_mul(size_of::<T>())
            .and_then(|n| n.checked_add(start))?;
        let values: &[T] = bytemuck::try_cast_slice(map.get(start..end)?).ok()?;
        // SAFETY: the slice points into the mapping that `map` owns. The
        // column holds `map` (an `Arc`) for as long as it holds the slice,
        // the mapping is never unmapped or moved while an `Mmap` owns it
        // (moving the `Mmap` value does not move the pages), and the slice
        // is only handed out with the lifetime of a borrow of the column.
        let values: &'static [T] = unsafe { std::mem::transmute::<&[T], &'static [T]>(values) };
        Some(Column::Mapped { map, values })
    }

    /// The values as a vector to change, copied out of the map first if
    /// they are mapped.
    pub(crate) fn to_mut(&mut self) -> &mut Vec<T> {
        if let Column::Mapped { .. } = self {
            *self = Column::Owned(self.to_vec());
        }
        match self {
            Column::Owned(v) => v,
            Column::Mapped { .. } => unreachable!("replaced by an owned copy above"),
        }
    }

    /// Whether the values are in a file mapping.
    pub(crate) fn is_mapped(&self) -> bool {
        matches!(self, Column::Mapped { .. })
    }
}

impl<T: bytemuck::Pod> Deref for Column<T> {
    type Target = [T];

    #[inline]
    fn deref(&self) -> &[T] {
        match self {
            Column::Owned(v) => v,
            Column::Mapped { values, .. } => values,
        }
    }
}

impl<T: 'static> Default for Column<T> {
    fn default() -> Self {
        Column::Owned(Vec::new())
    }
}

impl<T: Clone + 'static> Clone for Column<T> {
    fn clone(&self) -> Self {
        match self {
            Column::Owned(v) => Column::Owned(v.clone()),
            Column::Mapped { map, values } => Column::Mapped {
                map: map.clone(),
                values,
            },
        }
    }
}

impl<T: bytemuck::Pod + fmt::Debug> fmt::Debug for Column<T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.deref().fmt(f)
    }
}

impl<T: bytemuck::Pod + PartialEq> PartialEq for Column<T> {
    fn eq(&self, other: &Self) -> bool {
        self.deref() == other.deref()
    }
}
