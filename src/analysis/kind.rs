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
/// Shortest stretch of strong maxima (µm of arc) accepted as a filament. A point object's
/// maxima along any line through it are strong (≥ `STRONG_FRACTION` of its peak) only within
/// the focus: for a Gaussian focal spot of 1/e² radius w, over 2·w·√(ln 4 / 2) = 1.67 w, i.e.
/// ≈ 0.67 µm for the 0.4 µm focal radius of the paper's beam (≈ 0.8 µm measured on the vector
/// beam in focus; 1.2 µm is reached only ≈ 1 µm out of focus, where w has grown to 0.72 µm). A
/// filament's maxima are strong along its whole length in the scan. So the strong maxima must
/// span at least this much — whatever the scan's size: a scan crossing less of the line than
/// this cannot tell a filament from a point object, and is refused.
pub const MIN_FILAMENT_SPAN_UM: f64 = 1.2;
/// A maximum counts as strong only when it also stands this many of its 1σ above zero: noise
/// alone then makes a strong maximum with probability 0.13 % (one-sided Gaussian), and three of
/// five neighbouring lines (see [`check_filament_maxima`]) with probability ≈ 2·10⁻⁸.
pub const STRONG_SIGMA: f64 = 3.0;

/// A maximum below this fraction of the largest value of the whole sensitivity image is never
/// strong: it may be the tail or side lobe of a point object elsewhere in the scan (a point
/// object's tail falls below 2 % of its peak within ≈ 1.4 focal radii; see [`GAP_FLOOR`]). It
/// matters for noise-free data, where no noise threshold hides those tails: a bead at the
/// corner of a scan, outside the line, had the maxima of its side lobe (1.7 % of its peak) read
/// as a filament at 40°.
pub const TAIL_FRACTION: f64 = 0.02;

/// Check that the maxima along a fitted line form a filament, not one point object (a bead or
/// an aggregate, in noise or not). `lines`: every scan line the fitted line crosses, in line
/// order, as (arc position µm, maximum read there — NaN where none was), as for
/// [`check_filament_continuity`]; `sigma`: one maximum's 1σ (0 or NaN for noise-free data);
/// `image_max`: the largest value of the sensitivity image (same units; 0 or NaN: none).
/// Each line's maximum is replaced by the median of the five lines around it (0 where none was
/// read), so the ridge must be there line after line: a maximum that noise put on the line, or
/// a few noisy lines that happen to line up with the point object, do not count. The smoothed
/// maxima of at least `STRONG_FRACTION` of the largest and `STRONG_SIGMA`·σ are strong, and the
/// strong lines must span at least [`MIN_FILAMENT_SPAN_UM`] along the line (the focus's extent:
/// see there); no maximum below [`TAIL_FRACTION`] of `image_max` is strong. The check does not depend on the scan's size, position or pixel size (a point
/// object's strong maxima span the same length in µm in any scan), nor on the fraction of the
/// lines it covers.
pub fn check_filament_maxima(lines: &[(f64, f64)], sigma: f64, image_max: f64) -> Result<()> {
    let v: Vec<f64> = lines
        .iter()
        .map(|l| if l.1.is_finite() { l.1 } else { 0.0 })
        .collect();
    // Five lines around each, the lines beyond the scan's edge counted as 0 (no maximum read
    // there): at an end of the line, as in its middle, three of five lines must carry the ridge.
    // (A window cut short at the edge let two noisy maxima of the last three lines pass as
    // strong, so a lone bead plus edge noise spanned 2.3 µm at 0.1 µm pixels.)
    let at = |i: isize| -> f64 {
        if i < 0 || i as usize >= v.len() {
            0.0
        } else {
            v[i as usize]
        }
    };
    let smooth: Vec<f64> = (0..v.len() as isize)
        .map(|i| {
            let mut w = [at(i - 2), at(i - 1), at(i), at(i + 1), at(i + 2)];
            w.sort_by(f64::total_cmp);
            w[2]
        })
        .collect();
    let max = smooth.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
    let read = lines.iter().filter(|l| l.1.is_finite()).count();
    if read == 0 || max <= 0.0 || max.is_nan() {
        return Err(AnalysisError::Failed(
            "no filament found: no positive maximum along the line".into(),
        ));
    }
    let sigma = if sigma.is_finite() {
        sigma.max(0.0)
    } else {
        0.0
    };
    let floor = if image_max.is_finite() {
        TAIL_FRACTION * image_max.max(0.0)
    } else {
        0.0
    };
    let thr = (STRONG_FRACTION * max).max(STRONG_SIGMA * sigma).max(floor);
    let strong: Vec<f64> = lines
        .iter()
        .zip(&smooth)
        .filter(|(_, m)| **m >= thr)
        .map(|(l, _)| l.0)
        .collect();
    let span = strong.iter().cloned().fold(f64::NEG_INFINITY, f64::max)
        - strong.iter().cloned().fold(f64::INFINITY, f64::min);
    let span = if span.is_finite() { span } else { 0.0 };
    if span >= MIN_FILAMENT_SPAN_UM {
        return Ok(());
    }
    let crossed = (lines[lines.len() - 1].0 - lines[0].0).abs();
    let level = if floor >= thr {
        format!(
            "{:.0} % of the scan's largest maximum (a point object's tail)",
            TAIL_FRACTION * 100.0
        )
    } else if STRONG_SIGMA * sigma > STRONG_FRACTION * max {
        format!("{STRONG_SIGMA}σ of the noise")
    } else {
        format!("{:.0} % of the largest", STRONG_FRACTION * 100.0)
    };
    let tail = if crossed < MIN_FILAMENT_SPAN_UM {
        format!(
            " — the line crosses only {crossed:.2} µm of the scan ({} lines): a scan must cross at least {MIN_FILAMENT_SPAN_UM} µm of a filament to tell it from a point object",
            lines.len()
        )
    } else {
        " — this looks like a single point object (bead or aggregate); a filament measurement needs a filament crossing the scan".to_string()
    };
    Err(AnalysisError::Failed(format!(
        "the maxima do not form a filament: those above {level} span {span:.2} µm along the line, less than the {MIN_FILAMENT_SPAN_UM} µm a point object's focus cannot fill{tail}"
    )))
}

/// Longest stretch (µm of arc) between the strong maxima of a filament over which its signal
/// may fade into the noise: 1.5 focal radii. In the vector beam the negative side lobe of a
/// strong point object beside a faint filament cancels the filament's maxima over ≈ 0.45 µm
/// (a 17 nm protein filament beside aggregates at the paper's noise); point objects that happen
/// to lie on a line leave longer gaps once they are more than ≈ 1.7 µm apart (noise-free).
pub const MAX_GAP_UM: f64 = 0.6;
/// A line's maximum is filament signal where the running median (5 lines) of the maxima is at
/// least `GAP_SIGMA` times one maximum's 1σ, and at least `GAP_FLOOR` of the largest maximum
/// (the floor for noise-free data: a point object's tail falls below 2 % of its peak within
/// ≈ 1.4 focal radii).
pub const GAP_SIGMA: f64 = 2.0;
pub const GAP_FLOOR: f64 = 0.02;

/// Check that a filament's signal is continuous between its strong maxima, so that point
/// objects in a row are not read as a filament. `lines`: every scan line the fitted line
/// crosses, in line order, as (arc position µm, maximum read there — NaN where none was);
/// `sigma`: one maximum's 1σ. Over the lines between the first and the last maximum of at
/// least `STRONG_FRACTION` of the largest, the lines that are not filament signal — read, with
/// the median of the 5 nearest lines read below the threshold (see `GAP_SIGMA`), or not read
/// at all — must not run on for more than `MAX_GAP_UM`.
/// `angle_deg` names the line in the message.
pub fn check_filament_continuity(lines: &[(f64, f64)], sigma: f64, angle_deg: f64) -> Result<()> {
    let max = lines
        .iter()
        .map(|l| l.1)
        .filter(|v| v.is_finite())
        .fold(f64::NEG_INFINITY, f64::max);
    let strong = |l: &(f64, f64)| l.1.is_finite() && max > 0.0 && l.1 >= STRONG_FRACTION * max;
    let (Some(lo), Some(hi)) = (
        lines.iter().position(strong),
        lines.iter().rposition(strong),
    ) else {
        return Ok(());
    };
    if hi <= lo {
        return Ok(());
    }
    let span = &lines[lo..=hi];
    let sigma = if sigma.is_finite() { sigma } else { 0.0 };
    let thr = (GAP_SIGMA * sigma).max(GAP_FLOOR * max);
    let step = (span[span.len() - 1].0 - span[0].0).abs() / (span.len() - 1) as f64;
    // A line where no maximum was read says nothing (at coarse pixels a parabola on the flat
    // top of a broad ridge comes out convex in noise); a line read is filament signal where the
    // median of the five nearest lines read (itself, two before, two after) reaches the
    // threshold. A gap is a run of lines that are not signal: read below it, or not read.
    let read: Vec<usize> = (0..span.len()).filter(|&i| span[i].1.is_finite()).collect();
    let mut signal = vec![false; span.len()];
    for (j, &i) in read.iter().enumerate() {
        let mut w: Vec<f64> = read[j.saturating_sub(2)..(j + 3).min(read.len())]
            .iter()
            .map(|&k| span[k].1)
            .collect();
        w.sort_by(f64::total_cmp);
        signal[i] = w[w.len() / 2] >= thr;
    }
    // longest run of lines that are not signal: (start, length)
    let (mut best, mut run) = ((0, 0), (0, 0));
    for (i, s) in signal.iter().enumerate() {
        if !s {
            run = (if run.1 == 0 { i } else { run.0 }, run.1 + 1);
            if run.1 > best.1 {
                best = run;
            }
        } else {
            run = (0, 0);
        }
    }
    let gap = best.1 as f64 * step;
    if gap <= MAX_GAP_UM {
        return Ok(());
    }
    let arc0 = lines[0].0;
    let (a, b) = (
        (span[best.0].0 - arc0).abs(),
        (span[best.0 + best.1 - 1].0 - arc0).abs(),
    );
    let level = if GAP_SIGMA * sigma >= GAP_FLOOR * max {
        format!("{GAP_SIGMA}σ of the noise, {thr:.3}")
    } else {
        format!(
            "{:.0} % of the largest maximum, {thr:.3}",
            GAP_FLOOR * 100.0
        )
    };
    Err(AnalysisError::Failed(format!(
        "the maxima along the line at {angle_deg:.1}° do not form one filament: between its strong maxima, from {:.2} to {:.2} µm along the line ({gap:.2} µm; a filament fades for at most {MAX_GAP_UM} µm), no maximum stands above {level} — this looks like point objects (aggregates or beads) in a row, or a filament too faint to measure",
        a.min(b),
        a.max(b)
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
        let e_bead = check_filament_maxima(&bead, 0.0, 0.0)
            .unwrap_err()
            .to_string();
        assert!(e_bead.contains("point object"), "{e_bead}");
        // a flat filament with one aggregate twice as strong: accepted
        let mut fil: Vec<(f64, f64)> = (0..61).map(|i| (0.05 * i as f64, 0.4)).collect();
        fil[30].1 = 0.8;
        assert!(check_filament_maxima(&fil, 0.0, 0.0).is_ok());
        // a filament ending half-way through: strong over 1.5 µm of 3 µm
        let tip: Vec<(f64, f64)> = (0..61)
            .map(|i| (0.05 * i as f64, if i < 30 { 0.4 } else { 0.001 }))
            .collect();
        assert!(check_filament_maxima(&tip, 0.0, 0.0).is_ok());
        // the same bead in a scan crossing only 1.6 µm of the line, with the noise-free maxima
        // beyond it dropped (off the line) as noise drops them: strong over 0.70 µm, refused
        // (that it is strong on most of the lines read does not matter)
        let small: Vec<(f64, f64)> = bead
            .iter()
            .copied()
            .filter(|p| p.0.abs() <= 0.8 && p.1 > 0.05)
            .collect();
        let e = check_filament_maxima(&small, 0.0, 0.0)
            .unwrap_err()
            .to_string();
        assert!(e.contains("span 0.70 µm along the line"), "{e}");
        // one noise spike far from the bead (as strong as the bead) does not stretch its span,
        // nor do two lines side by side
        let mut spiked = bead.clone();
        spiked[5].1 = 1.0;
        spiked[6].1 = 1.0;
        let e_spiked = check_filament_maxima(&spiked, 0.0, 0.0)
            .unwrap_err()
            .to_string();
        assert_eq!(e_spiked, e_bead, "the spike stretched the bead's span");
        // lines without a maximum (NaN) count as no signal: a bead with a strong noise maximum
        // on the line every third line far away is still a bead
        let mut sparse = bead.clone();
        for (i, l) in sparse.iter_mut().enumerate() {
            if l.0.abs() > 0.5 {
                l.1 = if i % 3 == 0 { 0.5 } else { f64::NAN };
            }
        }
        let e_sparse = check_filament_maxima(&sparse, 0.0, 0.0)
            .unwrap_err()
            .to_string();
        assert_eq!(e_sparse, e_bead, "the far maxima stretched the bead's span");
        // a flat filament at 5σ is strong everywhere; at 2σ nothing stands above 3σ
        assert!(check_filament_maxima(&fil, 0.08, 0.0).is_ok());
        let e = check_filament_maxima(&tip, 0.2, 0.0)
            .unwrap_err()
            .to_string();
        assert!(e.contains("above 3σ of the noise span 0.00 µm"), "{e}");
        // a filament crossing a 1 µm scan: too short to tell
        let short: Vec<(f64, f64)> = (0..21).map(|i| (0.05 * i as f64, 0.4)).collect();
        let e = check_filament_maxima(&short, 0.0, 0.0)
            .unwrap_err()
            .to_string();
        assert!(e.contains("crosses only 1.00 µm"), "{e}");
    }

    /// Lines every 0.05 µm over 4 µm, values from `f(arc)`.
    fn lines(f: impl Fn(f64) -> f64) -> Vec<(f64, f64)> {
        (0..81)
            .map(|i| {
                let a = 0.05 * i as f64;
                (a, f(a))
            })
            .collect()
    }

    #[test]
    fn point_objects_in_a_row_are_not_one_filament() {
        let bump = |a: f64, c: f64| (-2.0 * (a - c).powi(2) / 0.16).exp(); // focal radius 0.4 µm
                                                                           // two point objects 2 µm apart, noise-free: 2 % of the peak is crossed 0.4·√(ln 50 / 2)
                                                                           // = 0.559 µm from each, so the lines at 1.60 … 2.40 µm (17 × 0.05 = 0.85 µm > 0.6 µm)
                                                                           // are below it
        let two = lines(|a| bump(a, 1.0) + bump(a, 3.0));
        let e = check_filament_continuity(&two, 0.0, -70.0)
            .unwrap_err()
            .to_string();
        assert!(e.contains("line at -70.0° do not form one filament"), "{e}");
        assert!(
            e.contains("from 1.60 to 2.40 µm along the line (0.85 µm;"),
            "{e}"
        );
        assert!(e.contains("above 2 % of the largest maximum, 0.020"), "{e}");
        // 1.5 µm apart: gap 0.4 µm, a short beaded filament to this check (documented limit)
        assert!(
            check_filament_continuity(&lines(|a| bump(a, 1.0) + bump(a, 2.5)), 0.0, 0.0).is_ok()
        );
        // a filament at 4σ with point objects 10× stronger on it, and missing lines (NaN): one
        // filament
        let fil = lines(|a| {
            if (a - 2.0).abs() < 0.01 {
                f64::NAN
            } else {
                0.4 + 4.0 * (bump(a, 0.5) + bump(a, 3.0))
            }
        });
        assert!(check_filament_continuity(&fil, 0.1, 0.0).is_ok());
        // the same filament fading below 2σ for 0.45 µm (a neighbour's negative side lobe): one
        // filament; for 0.7 µm: refused, and the threshold is 2σ = 0.2
        let dip = |w: f64| lines(move |a| if (a - 2.0).abs() < w / 2.0 { 0.1 } else { 0.4 });
        assert!(check_filament_continuity(&dip(0.45), 0.1, 0.0).is_ok());
        let e = check_filament_continuity(&dip(0.7), 0.1, 0.0)
            .unwrap_err()
            .to_string();
        assert!(e.contains("above 2σ of the noise, 0.200"), "{e}");
        // a filament ending half-way: nothing to check beyond its last strong maximum
        assert!(
            check_filament_continuity(&lines(|a| if a < 2.0 { 0.4 } else { 0.0 }), 0.1, 0.0)
                .is_ok()
        );
    }
}
