//! [`Template::from_scans`]: a template from measured scans of reference beads (Sec. 3.1). It
//! lives apart from `template.rs` because it aligns the beads with the multi-bead fit, which
//! itself evaluates templates: template ← fit ← template_from_scans, no import circle.

use super::fit::{fit_beads, BeadInit, FitOptions};
use super::peaks::peak_2d;
use super::profile::sample;
use super::sensitivity::{sensitivity, Axis, Stencil};
use super::template::{FromScansOptions, RefBead, Template, TemplateSource};
use super::{check_above, check_axis, AnalysisError, AxisMap, Result};
use crate::data::{Image, Scan};
use crate::optics::grid::{Grid2, Interp};

impl Template {
    /// Build a template from measured scans of reference beads (Sec. 3.1: "multiple scans … are
    /// aligned with each other and averaged"). Each scan may hold one or several well-separated
    /// beads. Steps: (1) locate beads as maxima of ∂Sx/∂x + ∂Sy/∂y (quadratic-surface sub-pixel
    /// peak); (2) resample every bead's (Sx, Sy, Sz) around its position on the template grid
    /// (bicubic) and average; (3) `iterations` times: fit each bead's position and weight to the
    /// current average with the multi-bead fit (one bead, eq. multiBeadFit), resample at the
    /// fitted positions, re-average; (4) normalise so max ∂Sx/∂x = 1.
    ///
    /// Beads closer than 2·`half_width_um` to another detected bead are skipped (their
    /// neighbours would contaminate the average). Nodes outside a scan get no contribution from
    /// it (`min_coverage` reports the least-covered node); nodes covered by no scan are 0.
    /// Errors: no scans, no isolated bead found, bad options.
    pub fn from_scans(
        scans: &[&Scan],
        reference: RefBead,
        opts: &FromScansOptions,
    ) -> Result<Template> {
        reference.validate()?;
        check_above("half_width_um", opts.half_width_um, 0.0)?;
        super::check_range("threshold", opts.threshold, 0.0, 1.0)?;
        if scans.is_empty() {
            return Err(AnalysisError::BadInput {
                name: "scans",
                reason: "no scans given".into(),
            });
        }
        let mut h = f64::INFINITY;
        let mut dets: Vec<(usize, Image)> = Vec::new();
        for (k, s) in scans.iter().enumerate() {
            check_axis("scan.x", &s.sx.x, 5)?;
            check_axis("scan.y", &s.sx.y, 5)?;
            if s.sy.data.dim() != s.sx.data.dim() || s.sz.data.dim() != s.sx.data.dim() {
                return Err(AnalysisError::BadInput {
                    name: "scans",
                    reason: format!("scan {k}: channels differ in shape"),
                });
            }
            h = h.min(s.sx.dx().abs()).min(s.sx.dy().abs());
            let a = sensitivity(&s.sx, Axis::X, Stencil::SavitzkyGolay { half_width: 2 })?;
            let b = sensitivity(&s.sy, Axis::Y, Stencil::SavitzkyGolay { half_width: 2 })?;
            dets.push((k, Image::new(&a.data + &b.data, a.x.clone(), a.y.clone())));
        }
        let h = opts.h_um.unwrap_or(h);
        check_above("h_um", h, 0.0)?;
        let hw = opts.half_width_um;
        let nn = (2.0 * hw / h).round() as usize + 1;
        if nn > 2001 {
            return Err(AnalysisError::OutOfRange {
                name: "h_um",
                value: h,
                allowed: format!("h_um ≥ {} for half_width_um = {hw}", hw / 1000.0),
            });
        }
        let u0 = -0.5 * (nn - 1) as f64 * h;

        // (1) Detection.
        let gmax = dets
            .iter()
            .flat_map(|(_, d)| d.data.iter().copied().filter(|v| v.is_finite()))
            .fold(f64::NEG_INFINITY, f64::max);
        if !(gmax > 0.0) {
            return Err(AnalysisError::Failed(
                "no bead found in the scans (∂Sx/∂x + ∂Sy/∂y is nowhere positive)".into(),
            ));
        }
        let mut found: Vec<(usize, f64, f64)> = Vec::new();
        for (k, d) in &dets {
            let mut work = d.clone();
            let limit = opts.beads_per_scan.unwrap_or(usize::MAX);
            let mut cands = Vec::new();
            while cands.len() < limit.min(1000) {
                let Ok(p) = peak_2d(&work, 0.4, None) else {
                    break;
                };
                if p.value < opts.threshold * gmax {
                    break;
                }
                cands.push((p.x, p.y));
                // Blank a disc of radius hw around it.
                for r in 0..work.rows() {
                    for c in 0..work.cols() {
                        if (work.x[c] - p.x).powi(2) + (work.y[r] - p.y).powi(2) < hw * hw {
                            work.data[[r, c]] = f64::NEG_INFINITY;
                        }
                    }
                }
            }
            for (i, &(x, y)) in cands.iter().enumerate() {
                let isolated = cands
                    .iter()
                    .enumerate()
                    .all(|(j, &(x2, y2))| j == i || (x - x2).hypot(y - y2) >= 2.0 * hw);
                if isolated || opts.beads_per_scan == Some(1) {
                    found.push((*k, x, y));
                }
            }
        }
        if found.is_empty() {
            return Err(AnalysisError::Failed(
                "no isolated reference bead found in the scans".into(),
            ));
        }

        // (2) First average.
        let mut tpl = average_beads(scans, &found, u0, h, nn, reference)?;
        let mut weights = vec![1.0; found.len()];
        // (3) Alignment by template fits.
        for _ in 0..opts.iterations {
            let mut refined = Vec::with_capacity(found.len());
            for (i, &(k, x, y)) in found.iter().enumerate() {
                let s = scans[k];
                let (cx, cy) = (crop(&s.sx, x, y, hw), crop(&s.sy, x, y, hw));
                let (Some(cx), Some(cy)) = (cx, cy) else {
                    refined.push((k, x, y));
                    continue;
                };
                let fo = FitOptions {
                    init: Some(vec![BeadInit { x, y, weight: 1.0 }]),
                    max_truncation: 1.0,
                    ..Default::default()
                };
                match fit_beads(&cx, &cy, &tpl.0, &fo) {
                    Ok(f)
                        if f.beads.len() == 1
                            && (f.beads[0].x - x).hypot(f.beads[0].y - y) < 0.5 =>
                    {
                        refined.push((k, f.beads[0].x, f.beads[0].y));
                        weights[i] = f.beads[0].weight;
                    }
                    _ => refined.push((k, x, y)),
                }
            }
            found = refined;
            tpl = average_beads(scans, &found, u0, h, nn, reference)?;
        }
        let (mut t, rms, cov) = tpl;
        let wm = weights.iter().sum::<f64>() / weights.len() as f64;
        t.source = TemplateSource::Scans {
            n_beads: found.len(),
            beads: found
                .iter()
                .zip(&weights)
                .map(|(&(k, x, y), w)| (k, x, y, w / wm))
                .collect(),
            rms_misfit: rms,
            min_coverage: cov,
        };
        Ok(t)
    }
}

/// Crop an image to the square of half-width `hw` around (x, y); None if fewer than 5×5 pixels.
pub(crate) fn crop(img: &Image, x: f64, y: f64, hw: f64) -> Option<Image> {
    let cr = AxisMap::new(&img.x).range(x - hw, x + hw);
    let rr = AxisMap::new(&img.y).range(y - hw, y + hw);
    if cr.len() < 5 || rr.len() < 5 {
        return None;
    }
    let data = img
        .data
        .slice(ndarray::s![rr.clone(), cr.clone()])
        .to_owned();
    Some(Image::new(data, img.x[cr].to_vec(), img.y[rr].to_vec()))
}

/// Average the beads' channels resampled on the template grid; returns the normalised template,
/// the RMS misfit of individual beads (template units) and the minimum node coverage.
fn average_beads(
    scans: &[&Scan],
    beads: &[(usize, f64, f64)],
    u0: f64,
    h: f64,
    nn: usize,
    reference: RefBead,
) -> Result<(Template, f64, f64)> {
    let mut sum = vec![[0.0f64; 3]; nn * nn];
    let mut sum2 = vec![0.0f64; nn * nn];
    let mut cnt = vec![0usize; nn * nn];
    for &(k, bx, by) in beads {
        let s = scans[k];
        for j in 0..nn {
            let v = u0 + j as f64 * h;
            for i in 0..nn {
                let u = u0 + i as f64 * h;
                let vals = [
                    sample(&s.sx, bx + u, by + v, Interp::Cubic),
                    sample(&s.sy, bx + u, by + v, Interp::Cubic),
                    sample(&s.sz, bx + u, by + v, Interp::Cubic),
                ];
                if let [Some(a), Some(b), c] = vals {
                    let idx = j * nn + i;
                    sum[idx][0] += a;
                    sum[idx][1] += b;
                    sum[idx][2] += c.unwrap_or(0.0);
                    sum2[idx] += a * a + b * b;
                    cnt[idx] += 1;
                }
            }
        }
    }
    let mut data = vec![[0.0f64; 3]; nn * nn];
    let mut ss = 0.0;
    let mut ns = 0usize;
    for idx in 0..nn * nn {
        if cnt[idx] > 0 {
            let c = cnt[idx] as f64;
            data[idx] = [sum[idx][0] / c, sum[idx][1] / c, sum[idx][2] / c];
            if cnt[idx] > 1 {
                let m2 = data[idx][0].powi(2) + data[idx][1].powi(2);
                ss += (sum2[idx] - c * m2).max(0.0);
                ns += 2 * (cnt[idx] - 1);
            }
        }
    }
    let min_cov = cnt.iter().copied().min().unwrap_or(0) as f64 / beads.len().max(1) as f64;
    let grid = Grid2::square(u0, h, nn, data, Interp::Cubic);
    let t = Template::normalised_with(
        grid,
        reference,
        TemplateSource::Scans {
            n_beads: beads.len(),
            beads: vec![],
            rms_misfit: 0.0,
            min_coverage: min_cov,
        },
        true,
    )?;
    let rms = if ns > 0 {
        (ss / ns as f64).sqrt() * t.norm_factor
    } else {
        0.0
    };
    Ok((t, rms, min_cov))
}
