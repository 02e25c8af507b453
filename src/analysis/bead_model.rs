//! The filament "bead model" (Sec. 4.2): a filament of radius r is cut into cylindrical sections
//! of height h (the bead spacing, paper: 50 nm); each section responds like a sphere of radius r
//! at its centre times the volume ratio 3h/(4r) (cylinder/sphere). Built from the TEMPLATE (a
//! measured or modelled reference bead), so instrument-specific features of the template
//! (misalignment, polarisation elongation) carry over to the filament.
//!
//! Weight of a section relative to the template's reference bead (diameter d_ref, index n_ref):
//! w = (d/d_ref)³ · n_corr(n, n_ref) · 3h/(2d) = 3·h·d²·n_corr / (2·d_ref³), so the weight per unit
//! length, 3d²·n_corr/(2d_ref³), is the cylinder's volume per length (πd²/4) over the reference
//! bead's volume (πd_ref³/6), times n_corr. The diameter may vary along the filament (linear
//! interpolation between vertices); sections are spaced evenly along the polyline (N = ⌈L/h⌉
//! sections of height L/N centred in their sub-segments).

use super::measure::MeasureOptions;
use super::peaks::{line_peaks, peak_near, LinePeak, PeakOptions};
use super::scaling::n_corr;
use super::sensitivity::{sensitivity, Axis};
use super::template::Template;
use super::{check_range, AnalysisError, Result};
use crate::data::{segment_lengths, Image, Scan};
use serde::{Deserialize, Serialize};

/// A filament: polyline (µm), diameter per vertex (nm; one value = uniform), refractive index.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Filament {
    pub points: Vec<[f64; 2]>,
    pub d_nm: Vec<f64>,
    pub n: f64,
}

impl Filament {
    /// Straight filament through `centre` at `angle_deg` from the QPD +y axis (towards +x),
    /// `length_um` long, uniform diameter.
    pub fn straight(centre: [f64; 2], angle_deg: f64, length_um: f64, d_nm: f64, n: f64) -> Self {
        let t = angle_deg.to_radians();
        let (dx, dy) = (0.5 * length_um * t.sin(), 0.5 * length_um * t.cos());
        Self {
            points: vec![
                [centre[0] - dx, centre[1] - dy],
                [centre[0] + dx, centre[1] + dy],
            ],
            d_nm: vec![d_nm],
            n,
        }
    }

    pub fn validate(&self) -> Result<()> {
        if self.points.len() < 2 {
            return Err(AnalysisError::BadInput {
                name: "points",
                reason: format!(
                    "{} vertices; a filament needs at least 2",
                    self.points.len()
                ),
            });
        }
        if self.points.iter().flatten().any(|v| !v.is_finite()) {
            return Err(AnalysisError::BadInput {
                name: "points",
                reason: "vertices must be finite (µm)".into(),
            });
        }
        if self.d_nm.len() != 1 && self.d_nm.len() != self.points.len() {
            return Err(AnalysisError::BadInput {
                name: "d_nm",
                reason: format!(
                    "{} diameters for {} vertices (give 1 or one per vertex)",
                    self.d_nm.len(),
                    self.points.len()
                ),
            });
        }
        for &d in &self.d_nm {
            check_range("d_nm", d, 0.0, 5000.0)?;
        }
        check_range("n", self.n, 1.0, 4.0)?;
        Ok(())
    }

    /// Total length, µm.
    pub fn length(&self) -> f64 {
        segment_lengths(&self.points).iter().sum()
    }
}

/// Options of the bead model.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct BeadModelOptions {
    /// Centre-to-centre spacing of the sections, nm (paper: 50 nm; must be well below w0).
    pub spacing_nm: f64,
}

impl Default for BeadModelOptions {
    fn default() -> Self {
        Self { spacing_nm: 50.0 }
    }
}

/// Weight (reference-bead units) of a cylindrical section of diameter `d_nm`, height `h_nm`,
/// index `n` (see the module docs). n_medium is the template's.
pub fn section_weight(tpl: &Template, d_nm: f64, h_nm: f64, n: f64) -> Result<f64> {
    let r = tpl.reference;
    let nc = n_corr(n, r.n, r.n_medium)?;
    Ok(1.5 * h_nm * d_nm * d_nm * nc / r.d_nm.powi(3))
}

/// The beads (x µm, y µm, weight) of a filament's bead model.
pub fn filament_beads(
    tpl: &Template,
    fil: &Filament,
    opts: &BeadModelOptions,
) -> Result<Vec<(f64, f64, f64)>> {
    fil.validate()?;
    check_range("spacing_nm", opts.spacing_nm, 1.0, 1000.0)?;
    let seg = segment_lengths(&fil.points);
    let total: f64 = seg.iter().sum();
    if !(total > 0.0) {
        return Err(AnalysisError::BadInput {
            name: "points",
            reason: "filament has zero length".into(),
        });
    }
    let h_um = opts.spacing_nm * 1e-3;
    let n = (total / h_um).ceil().max(1.0) as usize;
    if n > 2_000_000 {
        return Err(AnalysisError::OutOfRange {
            name: "spacing_nm",
            value: opts.spacing_nm,
            allowed: format!(
                "≥ {} nm for a {total} µm filament (at most 2·10⁶ sections)",
                total * 1e3 / 2e6
            ),
        });
    }
    let hs = total / n as f64;
    // Cumulative arc length at vertices, for the diameter profile.
    let mut cum = vec![0.0];
    for s in &seg {
        cum.push(cum.last().unwrap() + s);
    }
    let d_at = |t: f64| -> f64 {
        if fil.d_nm.len() == 1 {
            return fil.d_nm[0];
        }
        let k = cum
            .windows(2)
            .position(|w| t <= w[1])
            .unwrap_or(seg.len() - 1);
        let f = if seg[k] > 0.0 {
            ((t - cum[k]) / seg[k]).clamp(0.0, 1.0)
        } else {
            0.0
        };
        fil.d_nm[k] + f * (fil.d_nm[k + 1] - fil.d_nm[k])
    };
    let mut out = Vec::with_capacity(n);
    let mut k = 0;
    for i in 0..n {
        let t = (i as f64 + 0.5) * hs;
        while k + 1 < seg.len() && t > cum[k + 1] {
            k += 1;
        }
        let f = if seg[k] > 0.0 {
            ((t - cum[k]) / seg[k]).clamp(0.0, 1.0)
        } else {
            0.0
        };
        let (a, b) = (fil.points[k], fil.points[k + 1]);
        let w = section_weight(tpl, d_at(t), hs * 1e3, fil.n)?;
        out.push((a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), w));
    }
    Ok(out)
}

/// Render filaments and point beads ((x, y, weight) in reference-bead units) from the template
/// on the given axes (regular, µm): a noise-free scan by superposition (eq. ReEEpReEE).
pub fn render_scene(
    tpl: &Template,
    beads: &[(f64, f64, f64)],
    filaments: &[Filament],
    opts: &BeadModelOptions,
    x: &[f64],
    y: &[f64],
) -> Result<Scan> {
    super::check_axis("x", x, 1)?;
    super::check_axis("y", y, 1)?;
    let mut all = beads.to_vec();
    for f in filaments {
        all.extend(filament_beads(tpl, f, opts)?);
    }
    Ok(tpl.render_scan(&all, x, y))
}

/// Value of one line for averaging: the parabola peak, or (when the line has no proper peak,
/// e.g. a filament parallel to the line) the largest finite sample of the line (`lanes`:
/// Axis(0) rows, Axis(1) columns).
fn line_value(lp: &LinePeak, img: &Image, lanes: ndarray::Axis) -> Option<f64> {
    if let Some(p) = lp.peak() {
        return Some(p.value);
    }
    let m = img
        .data
        .index_axis(lanes, lp.line)
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .fold(f64::NEG_INFINITY, f64::max);
    m.is_finite().then_some(m)
}

/// Maximum sensitivities of a long straight uniform filament of the bead model at `angle_deg`
/// from the QPD y-axis, as the measurement pipeline sees them on pixels of `pixel_um`:
/// (mean over rows of the per-row maximum of ∂Sx/∂x, mean over columns of the per-column maximum
/// of ∂Sy/∂y), the rows/columns taken in a 9-pixel band through the filament's middle and the
/// filament shifted by 0, ¼, ½, ¾ pixel to average over its position relative to the pixels.
/// Each line's parabola is centred where the filament crosses it (as [`measure_filament`]
/// reads data); lines the filament crosses at a grazing angle (< 11.5°) or without a parabola
/// peak contribute their own maximum (parabola at the discrete maximum, or the largest sample).
///
/// [`measure_filament`]: super::orientation::measure_filament
pub fn straight_filament_max_sens(
    tpl: &Template,
    d_nm: f64,
    n: f64,
    angle_deg: f64,
    pixel_um: f64,
    measure: &MeasureOptions,
    bm: &BeadModelOptions,
) -> Result<(f64, f64)> {
    check_range("pixel_um", pixel_um, 1e-3, 1.0)?;
    check_range("angle_deg", angle_deg, -360.0, 360.0)?;
    measure.validate()?;
    let ((u0, u1), (v0, v1)) = tpl.extent();
    let ext = u0.abs().max(u1.abs()).max(v0.abs()).max(v1.abs());
    let field = 4.0f64.max(6.0 * measure.window_um);
    let nf = (field / pixel_um).round() as usize | 1;
    let full: Vec<f64> = (0..nf)
        .map(|i| (i as f64 - (nf / 2) as f64) * pixel_um)
        .collect();
    let band: Vec<f64> = (0..9).map(|i| (i as f64 - 4.0) * pixel_um).collect();
    let length = full[nf - 1] - full[0] + 2.1 * ext + 0.2;
    let popts = PeakOptions {
        window_um: measure.window_um,
        ..Default::default()
    };
    let (mut sx_acc, mut sy_acc, mut nsx, mut nsy) = (0.0, 0.0, 0usize, 0usize);
    for k in 0..4 {
        let off = k as f64 * pixel_um / 4.0;
        let fil = Filament::straight([off, off], angle_deg, length, d_nm, n);
        let beads = filament_beads(tpl, &fil, bm)?;
        let (sn, cs) = angle_deg.to_radians().sin_cos();
        // The row strip's Sx sensitivity (rows = true) or the column strip's Sy, and the maxima
        // of every row or column, each centred where the filament crosses its line, as
        // `measure_filament` reads data; a line the filament crosses at a grazing angle keeps
        // its own maximum.
        let lane_maxima = |rows: bool| -> Result<(f64, usize)> {
            let (xs, ys, axis) = if rows {
                (&full, &band, Axis::X)
            } else {
                (&band, &full, Axis::Y)
            };
            let [sx, sy, _] = tpl.render(&beads, xs, ys);
            let channel = if rows { sx } else { sy };
            let sens = &sensitivity(
                &Image::new(channel, xs.clone(), ys.clone()),
                axis,
                measure.stencil,
            )?;
            let (along, across) = if rows { (cs, sn) } else { (sn, cs) };
            let lanes = ndarray::Axis(if rows { 0 } else { 1 });
            let (mut acc, mut n) = (0.0, 0usize);
            for lp in line_peaks(sens, lanes, &popts)? {
                let lane = sens.data.index_axis(lanes, lp.line).to_vec();
                let at = off + (lp.coord - off) * across / along;
                let near = (along.abs() > 0.2)
                    .then(|| peak_near(&full, &lane, at, &popts).ok())
                    .flatten();
                if let Some(v) = near
                    .map(|p| p.value)
                    .or_else(|| line_value(&lp, sens, lanes))
                {
                    acc += v;
                    n += 1;
                }
            }
            Ok((acc, n))
        };
        let (a, n) = lane_maxima(true)?;
        sx_acc += a;
        nsx += n;
        let (a, n) = lane_maxima(false)?;
        sy_acc += a;
        nsy += n;
    }
    if nsx == 0 || nsy == 0 {
        return Err(AnalysisError::Failed(
            "bead-model filament gave no finite maxima".into(),
        ));
    }
    Ok((sx_acc / nsx as f64, sy_acc / nsy as f64))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn weights_sum_to_volume_ratio() {
        let tpl = Template::analytic_standin(0.4, 0.02, 1.6).unwrap();
        let r = tpl.reference;
        let fil = Filament {
            points: vec![[0.0, 0.0], [1.0, 0.0], [1.0, 2.0]],
            d_nm: vec![r.d_nm],
            n: r.n,
        };
        let beads = filament_beads(&tpl, &fil, &BeadModelOptions::default()).unwrap();
        assert_eq!(beads.len(), 60);
        let total: f64 = beads.iter().map(|b| b.2).sum();
        // 3 µm of a cylinder of the reference's diameter: (π d²/4·L)/(π d³/6) = 1.5 L/d.
        assert!((total - 1.5 * 3000.0 / r.d_nm).abs() < 1e-9, "{total}");
        // Sections lie on the polyline.
        assert!(beads
            .iter()
            .all(|b| (b.1.abs() < 1e-12 && b.0 <= 1.0) || (b.0 - 1.0).abs() < 1e-12));
        // Tapered: the diameter profile is interpolated (weight ∝ d²).
        let taper = Filament {
            points: vec![[0.0, 0.0], [0.0, 1.0]],
            d_nm: vec![0.0, 100.0],
            n: r.n,
        };
        let tb = filament_beads(&tpl, &taper, &BeadModelOptions::default()).unwrap();
        let ratio = tb[15].2 / tb[5].2;
        assert!((ratio - (15.5f64 / 5.5).powi(2)).abs() < 1e-9);
        let e = filament_beads(
            &tpl,
            &Filament {
                points: vec![[0.0, 0.0]],
                d_nm: vec![1.0],
                n: 1.5,
            },
            &BeadModelOptions::default(),
        )
        .unwrap_err()
        .to_string();
        assert_eq!(e, "points: 1 vertices; a filament needs at least 2");
    }
}
