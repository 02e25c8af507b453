//! The bead fit's domain (docs/analysis.md, "Domains"): the conditions under which the fitted
//! positions, weights and their σ hold, checked on the data and the fit, in words.
//!
//! - the optimiser converged;
//! - every bead is found (its weight significantly positive) and no bead was merged, dropped or
//!   left unresolved ([`Degeneracy`]);
//! - every bead is inside the point-dipole template's size domain: the diameter its weight
//!   implies for its index ([`FitOptions::bead_n`], default the reference's) stays below
//!   [`domain::dipole_d_max_nm`], where the template is off by less than 1 %;
//! - every bead lies whole inside the scan (its centre at least w0/2 inside the edge);
//! - the model describes the data: the residual's RMS is within [`MISFIT_RATIO`] of the pixel
//!   noise measured independently from the data ([`domain::pixel_noise`]).

use super::types::{Degeneracy, FitOptions, FitResult, FOUND_SIGMA};
use crate::analysis::domain;
use crate::analysis::template::Template;
use crate::data::Image;

/// The residual RMS may exceed the independent pixel-noise estimate by this factor before the
/// model is said not to describe the data (the two agree within a few % for a right model; the
/// estimate of the noise from first differences is itself good to ~2 % on 1 000 pixels).
pub const MISFIT_RATIO: f64 = 1.5;

/// Below this fraction of the signal's peak the residual RMS never counts as a misfit (a noise-free
/// image fitted by an interpolated template leaves ~1e-4 of the peak).
pub const MISFIT_FLOOR: f64 = 2e-3;

/// The diameter (nm) a bead of weight `w` (reference-bead units) has when made of index `n`: the
/// equal-polarisability sphere, d_ref·(w / n_corr)^⅓ (eq. nCor, Sec. 3.2). None for w ≤ 0.
pub fn implied_diameter_nm(w: f64, n: f64, tpl: &Template) -> Option<f64> {
    let r = &tpl.reference;
    let nc = crate::analysis::scaling::n_corr(n, r.n, r.n_medium).ok()?;
    (w > 0.0 && nc > 0.0).then(|| r.d_nm * (w / nc).cbrt())
}

/// The largest diameter (nm) the template describes for beads of index `n` (see the module docs).
pub fn d_max_nm(n: f64, tpl: &Template, opts: &FitOptions) -> f64 {
    domain::dipole_d_max_nm(n, opts.wavelength_nm, tpl.reference.n_medium)
}

/// Indices of the found beads whose implied diameter is outside the template's domain, with
/// that diameter.
pub(super) fn large_beads(r: &FitResult, tpl: &Template, opts: &FitOptions) -> Vec<(usize, f64)> {
    let n = opts.bead_n.unwrap_or(tpl.reference.n);
    let dmax = d_max_nm(n, tpl, opts);
    r.beads
        .iter()
        .enumerate()
        .filter(|(_, b)| b.found())
        .filter_map(|(i, b)| implied_diameter_nm(b.weight, n, tpl).map(|d| (i, d)))
        .filter(|&(_, d)| d > dmax)
        .collect()
}

/// The warnings of a finished fit of `sx`, `sy` (see the module docs).
pub(super) fn warnings(
    r: &FitResult,
    sx: &Image,
    sy: &Image,
    tpl: &Template,
    opts: &FitOptions,
) -> Vec<String> {
    let mut w = vec![];
    if r.status != super::FitStatus::Converged {
        w.push(format!(
            "the optimiser stopped before converging ({}): the values are not a least-squares minimum",
            r.reason
        ));
    }
    let found = r.beads.iter().filter(|b| b.found()).count();
    if found == 0 {
        w.push(format!(
            "no bead found: every fitted weight is consistent with noise (weight − {FOUND_SIGMA}σ ≤ 0)"
        ));
    } else {
        for (i, b) in r.beads.iter().enumerate().filter(|(_, b)| !b.found()) {
            w.push(format!(
                "bead {i} not found: weight {:.3}{} is consistent with noise; its position means nothing",
                b.weight,
                b.weight_err
                    .map(|e| format!(" ± {e:.3}"))
                    .unwrap_or_default()
            ));
        }
    }
    for d in &r.degeneracies {
        if let Some(s) = degeneracy_words(d) {
            w.push(s);
        }
    }
    let n = opts.bead_n.unwrap_or(tpl.reference.n);
    let dmax = d_max_nm(n, tpl, opts);
    for (i, d) in large_beads(r, tpl, opts) {
        w.push(format!(
            "bead {i}: its weight {:.3} implies a {d:.0} nm sphere of n = {n}, outside the point-dipole template's domain (d ≤ {dmax:.0} nm at this wavelength): its weight is biased by more than 1 % and σ does not include it; measure it with a template of its own size or the Mie tier",
            r.beads[i].weight
        ));
    }
    let margin = 0.5 * opts.w0_um;
    for (i, b) in r.beads.iter().enumerate().filter(|(_, b)| b.found()) {
        if let Some(s) = domain::margin_warning(&format!("bead {i}"), sx, b.x, b.y, margin) {
            w.push(s);
        }
    }
    if let Some(s) = misfit_words(r, sx, sy, opts) {
        w.push(s);
    }
    w
}

/// The residual RMS against the data's own pixel noise (see [`MISFIT_RATIO`]).
fn misfit_words(r: &FitResult, sx: &Image, sy: &Image, opts: &FitOptions) -> Option<String> {
    use super::types::Channels;
    if r.n_residuals == 0 {
        return None;
    }
    let imgs: Vec<&Image> = match opts.channels {
        Channels::Both => vec![sx, sy],
        Channels::Sx => vec![sx],
        Channels::Sy => vec![sy],
    };
    let noise2: f64 = imgs
        .iter()
        .map(|i| domain::pixel_noise(i, true).powi(2))
        .sum::<f64>()
        / imgs.len() as f64;
    let peak = imgs
        .iter()
        .flat_map(|i| i.data.iter())
        .filter(|v| v.is_finite())
        .fold(0.0f64, |m, v| m.max(v.abs()));
    let rms = (r.rss / r.n_residuals as f64).sqrt();
    let noise = noise2.sqrt();
    (rms > MISFIT_RATIO * noise && rms > MISFIT_FLOOR * peak).then(|| {
        format!(
            "the model does not describe the data: the residual RMS {rms:.3e} is {:.1}× the pixel noise {noise:.3e} (an object larger than a point, a filament, clipped pixels, or objects the fit did not take); the weights and σ assume it does",
            rms / noise.max(f64::MIN_POSITIVE)
        )
    })
}

/// A degeneracy in words, when it touches the answer (an ill-conditioned fit, a merge, a bead
/// dropped or unresolved; an insignificant bead is said by the not-found warning).
fn degeneracy_words(d: &Degeneracy) -> Option<String> {
    Some(match d {
        Degeneracy::CloseBeads {
            distance_um,
            merged,
            ..
        } => format!(
            "two beads {:.0} nm apart are degenerate{}",
            distance_um * 1000.0,
            if *merged {
                " and were merged into one"
            } else {
                ": their weights and positions trade off"
            }
        ),
        Degeneracy::Unresolved { distance_um, .. } => format!(
            "two beads {:.0} nm apart are not resolved by the data and were merged: the bead may be two",
            distance_um * 1000.0
        ),
        Degeneracy::BeadOutside { x, y, .. } => format!(
            "a bead left the image (last at ({x:.3}, {y:.3}) µm) and was dropped"
        ),
        Degeneracy::IllConditioned { condition } => format!(
            "the fit is ill-conditioned (condition number {condition:.1e}): no uncertainties"
        ),
        Degeneracy::Insignificant { .. } => return None,
    })
}
