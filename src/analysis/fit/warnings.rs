//! The bead fit's domain (docs/analysis.md, "Domains"): the conditions under which the fitted
//! positions, weights and their σ hold, checked on the data and the fit, in words.
//!
//! - the optimiser converged;
//! - a bead the fit searched for stands above the field's noise maxima ([`detection_sigma`]);
//! - every bead is found (its weight significantly positive) and no bead was merged, dropped or
//!   left unresolved ([`Degeneracy`]);
//! - no group of beads within w0 of each other, their weights trading off, weighs as much as a
//!   sphere outside that domain (one large object split by the fit);
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

/// The local misfit test's threshold, in standard deviations of χ² (√(2K)) above its mean K:
/// on pure noise it fires once in ~3·10⁶ beads.
pub const LOCAL_MISFIT_Z: f64 = 5.0;

/// A bead outside its domain biases the beads within this many beam waists w0 (its misfit
/// spreads over the derivative's reach: a pair merged at the scan's edge moved a bead 0.78 µm
/// away by 25 nm, 30σ, in the truth sweep). Its misfit also hides fainter objects within that
/// reach, which bias the beads within theirs: a bead within twice the reach is flagged too (a
/// 47 nm bead 0.44 µm from a 189 nm bead at the scan's edge went unfitted and moved a 131 nm
/// bead 1.0 µm from it, 1.3 µm from the large one, by 0.46 nm, 4.6σ, in the truth sweep).
pub const NEIGHBOUR_REACH_W0: f64 = 3.0;

/// A found bead fainter than this fraction of a bead outside its domain (anywhere in the scan)
/// may be the residue of that bead's misfit: a few % of a misfitted bead's signal, in side lobes
/// of a few % of its peak, leaves residuals of order 0.1 % of its weight across the field.
pub const FAINT_BESIDE_MISFIT: f64 = 0.01;

/// How often a searched field may give a false find: a bead placed on the detection map's
/// largest maximum (not at a position given in `init`) is the largest of the field's noise
/// maxima when there is no bead, not one Gaussian draw, so its weight is tested against
/// [`detection_sigma`] (the truth sweep found a "bead" of weight 0.024 ± 0.007, 3.5σ, in an empty
/// field at 8× the paper's noise).
pub const FALSE_FINDS_PER_FIELD: f64 = 1e-4;

/// The weight / σ a searched bead needs in a field of `area_um2` scanned with a focus of waist
/// `w0_um`: k with N·Φc(k) = [`FALSE_FINDS_PER_FIELD`] over N = area / w0² independent cells
/// (the detection map's correlation length is the focus's), one-sided Gaussian tails by Mills'
/// ratio Φc(k) < φ(k)/k (so k errs high, on the safe side). Never below `FOUND_SIGMA`. 4.5σ for
/// the sweep's 2.4 µm field in the paper's focus, 5.1σ for a 10 µm field.
pub fn detection_sigma(area_um2: f64, w0_um: f64) -> f64 {
    let n = (area_um2 / (w0_um * w0_um)).max(1.0);
    let mut k = FOUND_SIGMA;
    for _ in 0..30 {
        let arg = n / (FALSE_FINDS_PER_FIELD * k * (2.0 * std::f64::consts::PI).sqrt());
        k = (2.0 * arg.max(1.0).ln()).sqrt();
    }
    k.max(FOUND_SIGMA)
}

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

/// Sets the warnings of a finished fit of `sx`, `sy` (see the module docs): each bead's own in
/// `FitResult::bead_warnings`, and all of them, with those about the whole fit, in `FitResult::warnings`.
pub(super) fn attach(r: &mut FitResult, sx: &Image, sy: &Image, tpl: &Template, opts: &FitOptions) {
    let (all, per_bead) = warnings(r, sx, sy, tpl, opts);
    r.warnings = all;
    r.bead_warnings = per_bead;
}

/// The warnings of a finished fit (all of them), and each bead's own.
fn warnings(
    r: &FitResult,
    sx: &Image,
    sy: &Image,
    tpl: &Template,
    opts: &FitOptions,
) -> (Vec<String>, Vec<Vec<String>>) {
    let mut w = vec![];
    let mut own = vec![vec![]; r.beads.len()];
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
            own[i].push(format!(
                "bead {i} not found: weight {:.3}{} is consistent with noise; its position means nothing",
                b.weight,
                b.weight_err
                    .map(|e| format!(" ± {e:.3}"))
                    .unwrap_or_default()
            ));
        }
    }
    // A searched bead against the field's largest noise maximum (beads given in `init` are at
    // known positions: the 3σ of `found` holds for them).
    let given = opts.init.as_ref().map_or(0, Vec::len);
    let span = |a: &[f64]| {
        a.iter().copied().fold(f64::NEG_INFINITY, f64::max)
            - a.iter().copied().fold(f64::INFINITY, f64::min)
    };
    let k_det = detection_sigma(span(&sx.x) * span(&sx.y), opts.w0_um);
    for (i, b) in r
        .beads
        .iter()
        .enumerate()
        .skip(given)
        .filter(|(_, b)| b.found())
    {
        if let Some(e) = b.weight_err.filter(|e| *e > 0.0 && b.weight < k_det * e) {
            own[i].push(format!(
                "bead {i}: its weight {:.4} ± {e:.4} is {:.1}σ, below the {k_det:.1}σ that noise alone reaches once in {:.0} scans of a field this size (the fit searched the whole field for it): it may be noise",
                b.weight,
                b.weight / e,
                1.0 / FALSE_FINDS_PER_FIELD
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
        own[i].push(format!(
            "bead {i}: its weight {:.3} implies a {d:.0} nm sphere of n = {n}, outside the point-dipole template's domain (d ≤ {dmax:.0} nm at this wavelength): its weight is biased by more than 1 % and σ does not include it; measure it with a template of its own size or the Mie tier",
            r.beads[i].weight
        ));
    }
    for (i, w) in split_words(r, tpl, opts, n, dmax) {
        own[i].push(w);
    }
    let margin = 0.5 * opts.w0_um;
    for (i, b) in r.beads.iter().enumerate().filter(|(_, b)| b.found()) {
        if let Some(s) = domain::margin_warning(&format!("bead {i}"), sx, b.x, b.y, margin) {
            own[i].push(s);
        }
    }
    // One bead, not an unresolved pair or a larger object: the residual around each bead
    // against the data's own pixel noise.
    for (i, b) in r.beads.iter().enumerate() {
        if b.found() && own[i].is_empty() {
            if let Some(s) = local_misfit_words(i, r, sx, sy, opts) {
                own[i].push(s);
            }
        }
    }
    // A bead outside its domain is misfitted (its size, its part beyond the scan, a pair merged
    // at the edge): that misfit reaches its neighbours' values within the focus's reach.
    let reach = NEIGHBOUR_REACH_W0 * opts.w0_um;
    let outside: Vec<usize> = (0..r.beads.len())
        .filter(|&j| r.beads[j].found() && !own[j].is_empty())
        .collect();
    for (i, b) in r.beads.iter().enumerate() {
        if !b.found() || !own[i].is_empty() {
            continue;
        }
        // the nearest bead outside its domain: within its reach, its misfit biases bead i;
        // within twice it, the fainter object its misfit can hide does
        let nearest = outside
            .iter()
            .filter(|&&j| j != i)
            .map(|&j| (j, (r.beads[j].x - b.x).hypot(r.beads[j].y - b.y)))
            .min_by(|a, b| a.1.total_cmp(&b.1));
        match nearest {
            Some((j, d)) if d < reach => own[i].push(format!(
                "bead {i} is {d:.2} µm from bead {j}, which is outside its domain: bead {j}'s misfit reaches {reach:.2} µm and may bias bead {i}'s values beyond σ"
            )),
            Some((j, d)) if d < 2.0 * reach => own[i].push(format!(
                "bead {i} is {d:.2} µm from bead {j}, which is outside its domain: bead {j}'s misfit can hide a fainter object within {reach:.2} µm of it, whose own reach takes in bead {i} and may bias its values beyond σ"
            )),
            _ => {}
        }
    }
    // Beyond the reach, a misfitted bright bead still leaves its far side lobes' misfit across
    // the field: a bead fainter than FAINT_BESIDE_MISFIT of it may be that residue (a 274 nm
    // bead beyond the scan's edge, weight ≈ 7, left a "found" bead of weight 0.007 ± 0.001 at
    // 1.35 µm, where there was none).
    for (i, b) in r.beads.iter().enumerate() {
        if !b.found() || !own[i].is_empty() {
            continue;
        }
        if let Some(&j) = outside
            .iter()
            .filter(|&&j| j != i && b.weight.abs() < FAINT_BESIDE_MISFIT * r.beads[j].weight)
            .max_by(|&&a, &&c| r.beads[a].weight.total_cmp(&r.beads[c].weight))
        {
            own[i].push(format!(
                "bead {i} (weight {:.4}) is fainter than {:.0} % of bead {j} (weight {:.3}), which is outside its domain: it may be the residue of bead {j}'s misfit, whose side lobes reach across the scan, not a bead",
                b.weight,
                100.0 * FAINT_BESIDE_MISFIT,
                r.beads[j].weight
            ));
        }
    }
    if let Some(s) = misfit_words(r, sx, sy, opts) {
        w.push(s);
    }
    w.extend(own.iter().flatten().cloned());
    (w, own)
}

/// A split object, the other way round from [`large_beads`]: found beads within w0 of each
/// other whose weights trade off (one known to worse than [`SPLIT_WEIGHT_REL`]) and that together
/// weigh as much as a sphere of index `n` outside the domain (d > `dmax` nm) may be one large
/// object the fit split (a 205 nm bead 0.28 µm from the edge came out as three beads of weight
/// 1.8–2.7 ± 0.3–0.45, none outside the domain alone, in the truth sweep; three overlapping
/// 170 nm beads, each weight known to 0.05 %, are three). Each member's warning, by index.
fn split_words(
    r: &FitResult,
    tpl: &Template,
    opts: &FitOptions,
    n: f64,
    dmax: f64,
) -> Vec<(usize, String)> {
    let mut out = vec![];
    for (group, total, d) in split_groups(r, tpl, opts.w0_um, n, dmax) {
        let names = group
            .iter()
            .map(|i| i.to_string())
            .collect::<Vec<_>>()
            .join(", ");
        for &i in &group {
            out.push((i, format!(
                "beads {names} lie within w0 = {:.2} µm of each other, their weights trade off, and together they weigh {total:.3}, a {d:.0} nm sphere of n = {n}, outside the point-dipole template's domain (d ≤ {dmax:.0} nm): they may be one large object the fit split; measure it with a template of its size or the Mie tier",
                opts.w0_um
            )));
        }
    }
    out
}

/// The groups of [`split_words`]: members, total weight, implied diameter (nm).
fn split_groups(
    r: &FitResult,
    tpl: &Template,
    w0_um: f64,
    n: f64,
    dmax: f64,
) -> Vec<(Vec<usize>, f64, f64)> {
    close_groups(r, w0_um)
        .into_iter()
        .filter_map(|group| {
            let loose = group.iter().any(|&i| {
                let b = &r.beads[i];
                b.weight_err
                    .is_none_or(|e| e > SPLIT_WEIGHT_REL * b.weight.abs())
            });
            let total: f64 = group.iter().map(|&i| r.beads[i].weight).sum();
            let d = implied_diameter_nm(total, n, tpl).filter(|&d| d > dmax && loose)?;
            Some((group, total, d))
        })
        .collect()
}

/// The beads whose neighbourhood the grow step leaves alone, with the diameter (nm) of the
/// object they are part of: those outside the template's domain ([`large_beads`]) and the
/// members of a group that may be one large object the fit split ([`split_words`]). Beside
/// them the residual is the template's misfit of a large object, and each bead added there
/// splits it further (a 293 nm bead came out as five beads and a fit of 13 that took 50 s).
pub(super) fn grow_exclusions(
    r: &FitResult,
    tpl: &Template,
    opts: &FitOptions,
) -> Vec<(usize, f64)> {
    let n = opts.bead_n.unwrap_or(tpl.reference.n);
    let dmax = d_max_nm(n, tpl, opts);
    let mut out = large_beads(r, tpl, opts);
    for (group, _, d) in split_groups(r, tpl, opts.w0_um, n, dmax) {
        out.extend(group.into_iter().map(|i| (i, d)));
    }
    out
}

/// Beads of a group whose weights are known to worse than this fraction trade their weights
/// off: the group may be one object (see [`split_words`]).
pub const SPLIT_WEIGHT_REL: f64 = 0.05;

/// The groups of two or more found beads linked by distances under `reach` (µm), by index.
fn close_groups(r: &FitResult, reach: f64) -> Vec<Vec<usize>> {
    let found: Vec<usize> = (0..r.beads.len()).filter(|&i| r.beads[i].found()).collect();
    let mut group: Vec<usize> = (0..r.beads.len()).collect();
    let root = |g: &Vec<usize>, mut i: usize| {
        while g[i] != i {
            i = g[i];
        }
        i
    };
    for (k, &i) in found.iter().enumerate() {
        for &j in &found[k + 1..] {
            let (a, b) = (&r.beads[i], &r.beads[j]);
            if (a.x - b.x).hypot(a.y - b.y) < reach {
                let (ri, rj) = (root(&group, i), root(&group, j));
                group[ri.max(rj)] = ri.min(rj);
            }
        }
    }
    let mut out: std::collections::BTreeMap<usize, Vec<usize>> = Default::default();
    for &i in &found {
        out.entry(root(&group, i)).or_default().push(i);
    }
    out.into_values().filter(|g| g.len() > 1).collect()
}

/// The residual within w0 of bead `i` (both fitted channels) against the data's own pixel noise
/// ([`domain::pixel_noise`]): χ² over K pixels, flagged when it exceeds K by more than
/// [`LOCAL_MISFIT_Z`] of its spread √(2K) and its RMS exceeds [`MISFIT_FLOOR`] of the peak
/// signal (the template's own interpolation error at no noise).
fn local_misfit_words(
    i: usize,
    r: &FitResult,
    sx: &Image,
    sy: &Image,
    opts: &FitOptions,
) -> Option<String> {
    use super::types::Channels;
    let b = &r.beads[i];
    let chans: Vec<(&Image, &Image)> = match opts.channels {
        Channels::Both => vec![(sx, &r.residual_sx), (sy, &r.residual_sy)],
        Channels::Sx => vec![(sx, &r.residual_sx)],
        Channels::Sy => vec![(sy, &r.residual_sy)],
    };
    let rad = opts.w0_um;
    let (mut chi2, mut k, mut ss, mut peak) = (0.0, 0usize, 0.0, 0.0f64);
    for (data, res) in chans {
        // The noise of the residual's pixels where it is smaller than the data's: a large
        // object's steep signal fills the data's first differences (a 308 nm bead in a
        // 62-pixel field tripled it, and a 61 nm bead merged into its 167 nm neighbour 0.29 µm
        // away read as noise), while the residual's are the noise wherever the model fits.
        let sigma = match domain::pixel_noise(res, true) {
            s if s > 0.0 => s.min(domain::pixel_noise(data, true)),
            _ => domain::pixel_noise(data, true),
        };
        if !(sigma > 0.0) {
            return None;
        }
        for (row, &y) in res.y.iter().enumerate() {
            for (col, &x) in res.x.iter().enumerate() {
                if (x - b.x).hypot(y - b.y) > rad {
                    continue;
                }
                let (v, d) = (res.data[[row, col]], data.data[[row, col]]);
                if v.is_finite() && d.is_finite() {
                    chi2 += (v / sigma).powi(2);
                    ss += v * v;
                    k += 1;
                    peak = peak.max(d.abs());
                }
            }
        }
    }
    if k < 9 {
        return None;
    }
    let z = (chi2 - k as f64) / (2.0 * k as f64).sqrt();
    let rms = (ss / k as f64).sqrt();
    (z > LOCAL_MISFIT_Z && rms > MISFIT_FLOOR * peak).then(|| {
        format!(
            "bead {i}: the residual within {rad:.2} µm of it is {z:.1}σ above the pixel noise (χ² {chi2:.0} on {k} pixels): an unresolved pair, an object larger than a point, or a neighbour the fit did not take; its values assume one point bead"
        )
    })
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
