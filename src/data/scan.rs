//! `Scan`: the three QPD channels of one scan with their axes and metadata.

use super::image::Image;
use serde::{Deserialize, Serialize};

/// Whether a scan ran to its end.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ScanStatus {
    Complete,
    /// Stopped by the user (Ctrl-C); unmeasured pixels are NaN.
    Aborted,
    /// Stopped by a device error; unmeasured pixels are NaN.
    Failed,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Scan {
    pub sx: Image,
    pub sy: Image,
    pub sz: Image,
    pub status: ScanStatus,
    /// Free-form metadata (plan, optics, instrument, scene, script path/hash, time, pipeline).
    pub meta: serde_json::Value,
}

impl Scan {
    pub fn channel(&self, name: &str) -> Option<&Image> {
        match name {
            "sx" | "x" => Some(&self.sx),
            "sy" | "y" => Some(&self.sy),
            "sz" | "z" => Some(&self.sz),
            _ => None,
        }
    }
}
