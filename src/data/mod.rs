//! Scans, images, profiles and their files (npz, TIFF, CSV).

pub mod image;
pub mod scan;

pub use image::{Image, Profile};
pub use scan::{Scan, ScanStatus};
