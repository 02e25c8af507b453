//! The values scripts hold: [`ScanRef`] (`Scan`), [`ImageRef`] (`Image`), [`ProfileRef`]
//! (`Profile`). Large arrays sit behind `Arc`, so passing them around in scripts is cheap. A
//! leaf: the context keeps the last partial scan, `types.rs` (which re-exports these) binds
//! their properties, printing and arithmetic.

use crate::data::{Image, Profile, Scan};
use std::sync::Arc;

/// A scan in a script (`Scan`).
#[derive(Debug, Clone)]
pub struct ScanRef {
    pub scan: Arc<Scan>,
    /// Where it was saved, if it was.
    pub path: Option<Arc<str>>,
}

/// An image in a script (`Image`).
#[derive(Debug, Clone)]
pub struct ImageRef(pub Arc<Image>);

/// A 1-D curve in a script (`Profile`).
#[derive(Debug, Clone)]
pub struct ProfileRef(pub Arc<Profile>);

impl ScanRef {
    pub fn new(scan: Scan, path: Option<String>) -> Self {
        Self {
            scan: Arc::new(scan),
            path: path.map(Arc::from),
        }
    }
}
