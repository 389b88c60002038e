//! Typed structure-of-arrays columns, in memory or in memory-mapped
//! scratch files. Work in progress: see issue 4.
