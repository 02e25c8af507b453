//! What a scan is, and whether it fits what an analysis measures: the scan's plane from its
//! axis names (XY, XZ, YZ, or a line), and whether the maxima of a "filament" really form one.
//! Analysis refuses the wrong kind of input, naming what it found ("this is an XY scan;
//! focus_search needs an XZ or YZ scan").

use super::{AnalysisError, Result};
use crate::data::image::Image;

/// The kind of an image from its axes: `"XY"`, `"XZ"`, `"YZ"` (horizontal then vertical axis),
/// or `"line"` when it has a single row or column.
pub fn plane(img: &Image) -> String {
    if img.rows() <= 1 || img.cols() <= 1 {
        return "line".into();
    }
    format!("{}{}", img.x_name, img.y_name).to_uppercase()
}

/// Refuse an image whose plane is not one of `allowed`; `who` is the analysis.
pub fn require_plane(who: &str, img: &Image, allowed: &[&str]) -> Result<()> {
    let p = plane(img);
    let axes = format!("{}{}", img.x_name, img.y_name).to_uppercase();
    // a single row or column of an XY image is still lateral (fits with an initial guess work)
    if allowed.iter().any(|a| *a == p || *a == axes) {
        return Ok(());
    }
    let what = if p == "line" {
        "a line scan".to_string()
    } else {
        format!("an {p} scan")
    };
    Err(AnalysisError::BadInput {
        name: "scan",
        reason: format!(
            "this is {what}; {who} needs an {} scan",
            allowed.join(" or ")
        ),
    })
}

/// Fraction of the largest maximum that counts as "on the filament".
pub const STRONG_FRACTION: f64 = 0.25;
/// Shortest stretch of strong maxima (µm) accepted as a filament when they cover less than
/// half of the scan's lines: a point object (bead, aggregate) in focus gives ≈ 0.8 µm.
pub const MIN_FILAMENT_SPAN_UM: f64 = 1.2;

/// Check that maxima `(arc position µm, value)` along a fitted line form a filament, not one
/// point object: the maxima of at least `STRONG_FRACTION` of the largest must cover half of the
/// lines or span at least `MIN_FILAMENT_SPAN_UM`. A bead's row maxima line up perfectly but
/// are strong only over its own width.
pub fn check_filament_maxima(points: &[(f64, f64)]) -> Result<()> {
    let max = points
        .iter()
        .map(|p| p.1)
        .filter(|v| v.is_finite())
        .fold(f64::NEG_INFINITY, f64::max);
    if points.is_empty() || max <= 0.0 {
        return Err(AnalysisError::Failed(
            "no filament found: no positive maximum along the line".into(),
        ));
    }
    let strong: Vec<f64> = points
        .iter()
        .filter(|p| p.1 >= STRONG_FRACTION * max)
        .map(|p| p.0)
        .collect();
    let frac = strong.len() as f64 / points.len() as f64;
    let span = strong.iter().cloned().fold(f64::NEG_INFINITY, f64::max)
        - strong.iter().cloned().fold(f64::INFINITY, f64::min);
    if frac >= 0.5 || span >= MIN_FILAMENT_SPAN_UM {
        return Ok(());
    }
    Err(AnalysisError::Failed(format!(
        "the maxima do not form a filament: those above {:.0} % of the largest cover {span:.2} µm ({:.0} % of the {} lines) — this looks like a single point object (bead or aggregate); a filament measurement needs a filament crossing the scan",
        STRONG_FRACTION * 100.0,
        frac * 100.0,
        points.len()
    )))
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;

    fn img(x: &str, y: &str, rows: usize, cols: usize) -> Image {
        Image::new(
            Array2::zeros((rows, cols)),
            (0..cols).map(|i| i as f64).collect(),
            (0..rows).map(|i| i as f64).collect(),
        )
        .with_axis_names(x, y)
    }

    #[test]
    fn planes_and_refusals_name_what_was_found() {
        assert_eq!(plane(&img("x", "y", 5, 5)), "XY");
        assert_eq!(plane(&img("x", "z", 5, 5)), "XZ");
        assert_eq!(plane(&img("y", "z", 5, 5)), "YZ");
        assert_eq!(plane(&img("x", "y", 1, 5)), "line");
        let e = require_plane("focus_search", &img("x", "y", 5, 5), &["XZ", "YZ"]).unwrap_err();
        assert_eq!(
            e.to_string(),
            "scan: this is an XY scan; focus_search needs an XZ or YZ scan"
        );
        assert!(require_plane("fit_beads", &img("x", "y", 5, 5), &["XY"]).is_ok());
        assert!(require_plane("fit_beads", &img("x", "y", 5, 1), &["XY"]).is_ok());
        let e = require_plane("fit_beads", &img("x", "z", 5, 5), &["XY"]).unwrap_err();
        assert!(e
            .to_string()
            .contains("this is an XZ scan; fit_beads needs an XY scan"));
    }

    #[test]
    fn a_bead_is_not_a_filament() {
        // a Gaussian bump of FWHM 0.5 µm sampled every 0.05 µm over 3 µm: strong over ≈ 0.7 µm
        let bead: Vec<(f64, f64)> = (0..61)
            .map(|i| {
                let a = -1.5 + 0.05 * i as f64;
                (a, (-4.0 * 2f64.ln() * a * a / 0.25).exp())
            })
            .collect();
        let e = check_filament_maxima(&bead).unwrap_err().to_string();
        assert!(e.contains("point object"), "{e}");
        // a flat filament with one aggregate twice as strong: accepted
        let mut fil: Vec<(f64, f64)> = (0..61).map(|i| (0.05 * i as f64, 0.4)).collect();
        fil[30].1 = 0.8;
        assert!(check_filament_maxima(&fil).is_ok());
        // a filament ending half-way through: strong over 1.5 µm of 3 µm
        let tip: Vec<(f64, f64)> = (0..61)
            .map(|i| (0.05 * i as f64, if i < 30 { 0.4 } else { 0.001 }))
            .collect();
        assert!(check_filament_maxima(&tip).is_ok());
    }
}
