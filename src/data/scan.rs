//! `Scan`: the three QPD channels of one scan with their axes and metadata.

use super::image::Image;
use super::DataError;
use serde::{Deserialize, Serialize};
use std::fmt;

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
    /// Samples measured beside the images, kept so that nothing measured is lost: a raster
    /// scan's digitiser samples and the stage's recorded positions, one row per line
    /// (NaN-padded). Saved as `.npz` members `raw_<name>`; empty for point-by-point scans.
    #[serde(skip)]
    pub raw: Vec<(String, ndarray::Array2<f64>)>,
    /// Clipped samples and dark pixels per pixel ([`super::clip`]); saved as `.npz` members
    /// `clipped_sx`, `clipped_sy`, `clipped_sz`, `dark` when there are any.
    #[serde(skip)]
    pub flags: InputFlags,
}

impl ScanStatus {
    /// The lower-case name used in files and metadata (`"complete"`, `"aborted"`, `"failed"`).
    pub fn as_str(self) -> &'static str {
        match self {
            ScanStatus::Complete => "complete",
            ScanStatus::Aborted => "aborted",
            ScanStatus::Failed => "failed",
        }
    }

    /// Inverse of [`ScanStatus::as_str`].
    pub fn parse(s: &str) -> Result<ScanStatus, DataError> {
        match s {
            "complete" => Ok(ScanStatus::Complete),
            "aborted" => Ok(ScanStatus::Aborted),
            "failed" => Ok(ScanStatus::Failed),
            other => Err(DataError::invalid(
                "status",
                format!("{other:?}"),
                "one of \"complete\", \"aborted\", \"failed\"",
            )),
        }
    }
}

impl fmt::Display for ScanStatus {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl Scan {
    /// A scan that ran to its end from its three channels (sx, sy, sz) and metadata: no raw
    /// samples, no clipped or dark pixels.
    pub fn complete([sx, sy, sz]: [Image; 3], meta: serde_json::Value) -> Scan {
        Scan {
            sx,
            sy,
            sz,
            status: ScanStatus::Complete,
            meta,
            raw: Vec::new(),
            flags: InputFlags::default(),
        }
    }

    /// Check that the three channels share one shape, one pair of axes and axis names
    /// (required to save the scan: the file stores the axes once).
    pub fn check_consistent(&self) -> Result<(), DataError> {
        for (name, img) in [("sy", &self.sy), ("sz", &self.sz)] {
            if img.shape() != self.sx.shape() {
                return Err(DataError::ShapeMismatch {
                    op: if name == "sy" {
                        "scan channels sx vs sy"
                    } else {
                        "scan channels sx vs sz"
                    },
                    left: self.sx.shape(),
                    right: img.shape(),
                });
            }
            let same_axes = bits_eq(&img.x, &self.sx.x) && bits_eq(&img.y, &self.sx.y);
            if !same_axes || img.x_name != self.sx.x_name || img.y_name != self.sx.y_name {
                return Err(DataError::invalid(
                    &format!("{name} axes"),
                    format!(
                        "{} {} / {} {}",
                        img.x_name,
                        img.x.len(),
                        img.y_name,
                        img.y.len()
                    ),
                    "all three channels of a scan must share the axes of sx",
                ));
            }
        }
        Ok(())
    }

    pub fn channel(&self, name: &str) -> Option<&Image> {
        match name {
            "sx" | "x" => Some(&self.sx),
            "sy" | "y" => Some(&self.sy),
            "sz" | "z" => Some(&self.sz),
            _ => None,
        }
    }
}

fn bits_eq(a: &[f64], b: &[f64]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(p, q)| p.to_bits() == q.to_bits())
}

impl fmt::Display for Scan {
    /// One line: status, shape, axes and the Sx/Sy/Sz ranges.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let i = &self.sx;
        write!(
            f,
            "Scan ({}) {}x{} (rows x cols)",
            self.status,
            i.rows(),
            i.cols()
        )?;
        for (name, axis) in [(&i.x_name, &i.x), (&i.y_name, &i.y)] {
            match axis.as_slice() {
                [] => write!(f, ", {name} empty")?,
                [v] => write!(f, ", {name} {} µm", super::image::fmt_sig(*v, 5))?,
                a => write!(
                    f,
                    ", {name} {}..{} µm",
                    super::image::fmt_sig(a[0], 5),
                    super::image::fmt_sig(a[a.len() - 1], 5)
                )?,
            }
        }
        for (name, img) in [("sx", &self.sx), ("sy", &self.sy), ("sz", &self.sz)] {
            match (img.min(), img.max()) {
                (Ok(lo), Ok(hi)) => write!(
                    f,
                    ", {name} {}..{}",
                    super::image::fmt_sig(lo, 4),
                    super::image::fmt_sig(hi, 4)
                )?,
                _ => write!(f, ", {name} no data")?,
            }
        }
        let nan = self.sx.nan_count();
        if nan > 0 {
            write!(f, ", {nan} unmeasured pixels")?;
        }
        Ok(())
    }
}

/// Per-pixel flags of a scan's inputs (empty: nothing clipped, nothing dark, or not counted).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct InputFlags {
    /// Samples at or beyond the rail per pixel, for Sx, Sy, Sz; `None` when no sample of that
    /// channel was.
    pub clipped: [Option<ndarray::Array2<u32>>; 3],
    /// 1 where the pixel's sum was below the floor; `None` when no pixel was.
    pub dark: Option<ndarray::Array2<u8>>,
}

impl InputFlags {
    /// No pixel clipped or dark.
    pub fn is_empty(&self) -> bool {
        self.clipped.iter().all(Option::is_none) && self.dark.is_none()
    }
}
