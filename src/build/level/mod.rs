//! Breadth-first level builder (Wu, Zhao & Liu, HPG 2011, on CPU cores).
//! Work in progress: see issue 4.
