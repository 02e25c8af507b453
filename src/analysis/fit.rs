//! Multi-bead template fit (eq. multiBeadFit, Sec. 4.1; suppl. S7 with 11 beads):
//!
//! f(C₁, x₁, y₁, …, Cₙ, xₙ, yₙ) = ( Σᵢ Cᵢ Sx(x − xᵢ, y − yᵢ) , Σᵢ Cᵢ Sy(x − xᵢ, y − yᵢ) )
//!
//! fitted by least squares to the Sx and Sy images together (or to one channel, for the
//! background removal of Sec. 6) by Levenberg–Marquardt (our own, on the normal equations). The images are in
//! instrument units (as measured or simulated); the template converts: its normalised response
//! divided by `norm_factor` is the reference bead in instrument units, so the weights Cᵢ come out
//! in reference-bead units (a bead identical to the template's reference has C = 1; C scales with
//! volume × n_corr, Sec. 3.2). Positions in µm (stage coordinates); model and residual images and
//! σ in instrument units.
//!
//! **Jacobian.** Analytic, from the template's interpolant: ∂r/∂Cᵢ = S(s − pᵢ),
//! ∂r/∂xᵢ = −Cᵢ ∂S/∂u, ∂r/∂yᵢ = −Cᵢ ∂S/∂v (`Grid2::eval_grad`). Each bead only touches the pixels
//! inside the template's extent around it.
//!
//! **Normal equations (speed).** The residual vector has one entry per valid pixel and
//! channel (32 768 for a 128×128 two-channel fit). Instead of forming that M×N Jacobian (whose
//! QR costs O(M·N²) per iteration), each evaluation accumulates the Gauss–Newton matrix JᵀJ, the
//! gradient Jᵀr and ‖r‖² bead by bead over each bead's window (JᵀJ is block-sparse: a pair of
//! beads couples only through the overlap of their windows; see `FitData::accumulate`, linear in
//! the number of beads), and the Levenberg–Marquardt steps solve (JᵀJ + λD²)δ = −Jᵀr by a
//! Cholesky factorisation that skips the zero blocks left of each row's profile (see
//! `levenberg_marquardt`: Moré's scaling D, gain-ratio step acceptance, MINPACK's ftol / xtol /
//! gtol tests). The last accepted evaluation also gives the statistics at the solution.
//!
//! **Uncertainties** from the covariance σ²(JᵀJ)⁻¹ at the solution, σ the given pixel noise
//! or, if absent, √(RSS/(m − 3n)).
//!
//! **Degeneracy** (the optimiser reports `Converged` for a fully degenerate fit — one weight
//! absorbing the other, the lost bead's position wandering off). After every fit:
//! beads closer than `min_separation` × w0 (default w0/4) are reported
//! ([`Degeneracy::CloseBeads`]) and, with `merge_degenerate` (default), merged (weights summed,
//! positions |C|-weighted) and the fit repeated; pairs closer than `resolve_separation` × w0
//! (default w0/2) are refitted merged and kept merged when that does not raise the BIC or when
//! one of them has a weight consistent with zero — the data do not resolve them
//! ([`Degeneracy::Unresolved`]; this catches a degenerate pair that noise pushed apart, e.g. two
//! beads 60 nm apart fitted as 1.87 + 0.12 ± 0.20 at 123 nm); beads that
//! left the region their template can reach are reported and dropped; weights consistent with
//! zero are reported ([`Degeneracy::Insignificant`], the position is then meaningless); the
//! condition number of the column-scaled JᵀJ is reported and, above `cond_limit`,
//! [`Degeneracy::IllConditioned`] is reported and the uncertainties are `None`. Weights and
//! positions are therefore always finite and never "wild".
//!
//! **Initial guesses** (when `init` is not given): CLEAN on the detection map
//! D = ∂Sx/∂x + ∂Sy/∂y (or the one fitted channel's sensitivity): the highest maximum gives a bead
//! (sub-pixel by parabolas, weight from its height relative to the template's own D peak), its
//! template D response is subtracted, repeat. **Adding beads** (`grow`): after a fit, a bead is
//! added at the largest maximum of the residual's D map and all beads are refitted; the larger
//! model is kept while the criterion improves (BIC by default: χ² + k ln m with known σ, else
//! m ln(RSS/m) + k ln m, k = 3n; or a relative RSS drop of at least `min_drop`).
//!
//! **Limits** (clear errors): images of different shapes or irregular axes; no valid pixel; a
//! template truncated at its border by more than `max_truncation` of its peak (it does not cover
//! the response it must represent); an initial bead farther outside the image than the
//! template reaches; more beads than the image supports — each bead needs its own
//! (min_separation·w0)² patch of the scanned area and the fit needs more residuals than
//! parameters.

mod lm;

pub use lm::FitStatus;
use lm::{levenberg_marquardt, scaled_condition, RawFit, Tolerances};

use super::sensitivity::{sensitivity, Axis, Stencil};
use super::template::Template;
use super::{check_above, check_axis, check_range, AnalysisError, AxisMap, Result};
use crate::data::Image;
use crate::optics::grid::GradStencil;
use nalgebra::{DMatrix, DVector};
use ndarray::Array2;
use serde::{Deserialize, Serialize};

/// Which channels enter the fit.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Channels {
    /// Sx and Sy together (eq. multiBeadFit).
    #[default]
    Both,
    Sx,
    Sy,
}

impl Channels {
    fn list(&self) -> &'static [usize] {
        match self {
            Channels::Both => &[0, 1],
            Channels::Sx => &[0],
            Channels::Sy => &[1],
        }
    }
    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "both" | "xy" => Some(Channels::Both),
            "sx" | "x" => Some(Channels::Sx),
            "sy" | "y" => Some(Channels::Sy),
            _ => None,
        }
    }
}

/// An initial guess: position (µm) and weight (reference-bead units).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct BeadInit {
    pub x: f64,
    pub y: f64,
    pub weight: f64,
}

/// Stopping rule when adding beads one at a time.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum GrowCriterion {
    /// Bayesian information criterion must decrease.
    Bic,
    /// RSS must drop by at least this fraction (e.g. 0.02 = 2 %).
    RelDrop { min_drop: f64 },
}

/// Options of [`fit_beads`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct FitOptions {
    pub channels: Channels,
    /// Number of beads for automatic initial guesses (ignored when `init` is given). With neither
    /// `n_beads` nor `init`, the fit grows from one bead (as with `grow`).
    pub n_beads: Option<usize>,
    /// Initial guesses.
    pub init: Option<Vec<BeadInit>>,
    /// Add beads one at a time at the largest residual while `criterion` improves.
    pub grow: bool,
    /// Upper limit on the number of beads when growing.
    pub max_beads: usize,
    pub criterion: GrowCriterion,
    /// Pixel noise σ (signal units); None: estimated from the residuals.
    pub sigma: Option<f64>,
    /// Relative tolerances of the optimiser (ftol on the objective, xtol on the parameters, gtol
    /// on the gradient–residual cosine; MINPACK's meaning).
    pub ftol: f64,
    pub xtol: f64,
    pub gtol: f64,
    /// Residual evaluations allowed = patience × (3n + 1).
    pub patience: usize,
    /// Beam waist, µm (sets the degeneracy distance); the `fit_beads` binding takes it from the
    /// session's optics (`set_optics(#{w0_nm})`).
    pub w0_um: f64,
    /// Beads closer than `min_separation × w0_um` are degenerate (default 1/4).
    pub min_separation: f64,
    /// Merge degenerate pairs and refit (default true); false: only report them.
    pub merge_degenerate: bool,
    /// Pairs closer than `resolve_separation × w0_um` (default 1/2) are tested: if merging them
    /// does not raise the BIC, the data do not resolve them and they are merged
    /// ([`Degeneracy::Unresolved`]). 0 disables the test.
    pub resolve_separation: f64,
    /// Condition number of the column-scaled JᵀJ above which the fit is reported ill-conditioned.
    pub cond_limit: f64,
    /// Largest allowed template border value relative to its peak.
    pub max_truncation: f64,
    /// Derivative used for the detection map.
    pub detect_stencil: Stencil,
}

impl Default for FitOptions {
    fn default() -> Self {
        Self {
            channels: Channels::Both,
            n_beads: None,
            init: None,
            grow: false,
            max_beads: 30,
            criterion: GrowCriterion::Bic,
            sigma: None,
            ftol: 1e-10,
            xtol: 1e-10,
            gtol: 1e-10,
            patience: 100,
            w0_um: 0.4,
            min_separation: 0.25,
            merge_degenerate: true,
            resolve_separation: 0.5,
            cond_limit: 1e10,
            max_truncation: 0.05,
            detect_stencil: Stencil::SavitzkyGolay { half_width: 2 },
        }
    }
}

impl FitOptions {
    fn validate(&self) -> Result<()> {
        check_range("ftol", self.ftol, 0.0, 1.0)?;
        check_range("xtol", self.xtol, 0.0, 1.0)?;
        check_range("gtol", self.gtol, 0.0, 1.0)?;
        check_range("patience", self.patience as f64, 1.0, 1e6)?;
        check_range("w0_um", self.w0_um, 0.01, 100.0)?;
        check_range("min_separation", self.min_separation, 0.0, 10.0)?;
        check_range("resolve_separation", self.resolve_separation, 0.0, 10.0)?;
        check_above("cond_limit", self.cond_limit, 1.0)?;
        check_range("max_truncation", self.max_truncation, 0.0, 1.0)?;
        check_range("max_beads", self.max_beads as f64, 1.0, 10_000.0)?;
        if let Some(s) = self.sigma {
            check_above("sigma", s, 0.0)?;
        }
        if let GrowCriterion::RelDrop { min_drop } = self.criterion {
            check_range("min_drop", min_drop, 0.0, 1.0)?;
        }
        if let Some(n) = self.n_beads {
            if n == 0 {
                return Err(AnalysisError::OutOfRange {
                    name: "n_beads",
                    value: 0.0,
                    allowed: "n_beads ≥ 1".into(),
                });
            }
        }
        if let Some(init) = &self.init {
            if init.is_empty() {
                return Err(AnalysisError::BadInput {
                    name: "init",
                    reason: "empty list of initial beads".into(),
                });
            }
            for (i, b) in init.iter().enumerate() {
                for (key, v) in [("x", b.x), ("y", b.y), ("weight", b.weight)] {
                    if !v.is_finite() {
                        return Err(AnalysisError::BadInput {
                            name: "init",
                            reason: format!("bead {i}: {key} = {v}; initial values must be finite"),
                        });
                    }
                }
            }
        }
        Ok(())
    }
}

/// A fitted bead.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Bead {
    /// Position, µm.
    pub x: f64,
    pub y: f64,
    /// Weight Cᵢ, reference-bead units.
    pub weight: f64,
    /// 1σ uncertainties; None when the fit is ill-conditioned (see `degeneracies`).
    pub x_err: Option<f64>,
    pub y_err: Option<f64>,
    pub weight_err: Option<f64>,
}

/// A bead is found when its weight is significantly positive: C − `FOUND_SIGMA`·σ_C > 0. Three
/// standard deviations, one-sided: on pure noise a fitted bead passes with probability 0.13 %
/// (Gaussian), where 2σ would "find" one bead in 44; a real bead at the paper's noise (weights
/// known to a few %) passes by a wide margin.
pub const FOUND_SIGMA: f64 = 3.0;

impl Bead {
    /// Whether the weight is significantly positive (see [`FOUND_SIGMA`]). Without an
    /// uncertainty (an ill-conditioned fit, reported in `degeneracies`) a positive weight counts.
    pub fn found(&self) -> bool {
        match self.weight_err {
            Some(e) if e.is_finite() => self.weight - FOUND_SIGMA * e > 0.0,
            _ => self.weight.is_finite() && self.weight > 0.0,
        }
    }
}

/// A degeneracy found in the fit.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Degeneracy {
    /// Two beads closer than min_separation·w0 (positions of the pair, their weights, distance
    /// in µm); `merged` tells whether they were merged into one bead.
    CloseBeads {
        a: [f64; 3],
        b: [f64; 3],
        distance_um: f64,
        merged: bool,
    },
    /// A bead moved out of reach of the image (its template no longer overlaps valid pixels)
    /// and was dropped.
    BeadOutside { x: f64, y: f64, weight: f64 },
    /// Two beads closer than resolve_separation·w0 that the data do not resolve (the merged
    /// model's BIC is lower by `delta_bic`, or one weight is consistent with zero); they were
    /// merged.
    Unresolved {
        a: [f64; 3],
        b: [f64; 3],
        distance_um: f64,
        delta_bic: f64,
    },
    /// A bead whose weight is consistent with zero (|C| < 2σ_C, or |C| < 1e-9): its position is
    /// meaningless. Kept in the result (it is part of the least-squares solution).
    Insignificant {
        x: f64,
        y: f64,
        weight: f64,
        weight_err: Option<f64>,
    },
    /// Column-scaled JᵀJ has a condition number above `cond_limit`.
    IllConditioned { condition: f64 },
}

/// One step of the bead-adding procedure.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct GrowStep {
    pub n_beads: usize,
    pub rss: f64,
    pub bic: f64,
    pub accepted: bool,
}

/// Result of [`fit_beads`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FitResult {
    pub beads: Vec<Bead>,
    /// Model images (both channels, whatever was fitted) and residuals data − model (NaN where
    /// the data are NaN).
    pub model_sx: Image,
    pub model_sy: Image,
    pub residual_sx: Image,
    pub residual_sy: Image,
    /// Σ (data − model)² over the fitted channels' valid pixels.
    pub rss: f64,
    /// rss / σ².
    pub chi2: f64,
    /// Residuals m minus parameters 3n.
    pub dof: usize,
    pub n_residuals: usize,
    /// σ used for uncertainties and χ², and whether it was estimated from the residuals.
    pub sigma: f64,
    pub sigma_estimated: bool,
    pub bic: f64,
    /// Jacobian evaluations (= accepted LM iterations + 1) and residual evaluations of the final
    /// fit (and summed over all refits in `total_evaluations`).
    pub iterations: usize,
    pub evaluations: usize,
    pub total_evaluations: usize,
    pub status: FitStatus,
    /// The optimiser's termination reason, in words.
    pub reason: String,
    /// Condition number of the column-scaled JᵀJ (capped at 1e300 when singular).
    pub condition: f64,
    pub degeneracies: Vec<Degeneracy>,
    /// Bead-adding history (empty when not growing).
    pub history: Vec<GrowStep>,
}

impl FitResult {
    pub fn is_degenerate(&self) -> bool {
        !self.degeneracies.is_empty()
    }
    /// The beads whose weight is not significantly positive ([`Bead::found`]): not found.
    pub fn not_found(&self) -> Vec<&Bead> {
        self.beads.iter().filter(|b| !b.found()).collect()
    }
    /// Σ weights (reference-bead units).
    pub fn total_weight(&self) -> f64 {
        self.beads.iter().map(|b| b.weight).sum()
    }
}

/// Fit `n` shifted, weighted copies of `tpl` to the scan channels `sx`, `sy` (eq.
/// multiBeadFit). See the module docs for the method, outcomes and errors.
pub fn fit_beads(sx: &Image, sy: &Image, tpl: &Template, opts: &FitOptions) -> Result<FitResult> {
    opts.validate()?;
    super::kind::require_plane("fit_beads", sx, &["XY"])?;
    let data = FitData::new(sx, sy, tpl, opts)?;
    let grow = opts.grow || (opts.init.is_none() && opts.n_beads.is_none());
    let init: Vec<BeadInit> = match &opts.init {
        Some(b) => b.clone(),
        None => {
            let n = if grow { 1 } else { opts.n_beads.unwrap_or(1) };
            data.check_count(n)?;
            let d = detection_map(sx, sy, opts.channels, opts.detect_stencil)?;
            let found = clean(&d, tpl, opts.channels, n, 0.0, 0.0);
            if found.is_empty() {
                return Err(AnalysisError::Failed(
                    "no bead found: the detection map ∂Sx/∂x + ∂Sy/∂y has no positive maximum"
                        .into(),
                ));
            }
            found
        }
    };
    data.check_count(init.len())?;
    for (i, b) in init.iter().enumerate() {
        if !data.reaches(b.x, b.y) {
            let ((u0, u1), (v0, v1)) = tpl.extent();
            return Err(AnalysisError::TemplateCoverage(format!(
                "initial bead {i} at ({}, {}) µm is farther outside the image than the template reaches (u ∈ [{u0}, {u1}], v ∈ [{v0}, {v1}] µm)",
                b.x, b.y
            )));
        }
    }
    let mut best = data.fit_with_degeneracy(init, opts)?;
    if grow {
        let mut history = vec![GrowStep {
            n_beads: best.beads.len(),
            rss: best.rss,
            bic: best.bic,
            accepted: true,
        }];
        while best.beads.len() < opts.max_beads && data.check_count(best.beads.len() + 1).is_ok() {
            let Ok(d) = detection_map(
                &best.residual_sx,
                &best.residual_sy,
                opts.channels,
                opts.detect_stencil,
            ) else {
                break;
            };
            let existing: Vec<BeadInit> = best
                .beads
                .iter()
                .map(|b| BeadInit {
                    x: b.x,
                    y: b.y,
                    weight: b.weight,
                })
                .collect();
            let new = clean(&d, tpl, opts.channels, 1, 0.0, 0.0);
            let Some(nb) = new.first().copied() else {
                break;
            };
            let mut init = existing.clone();
            init.push(nb);
            let cand = data.fit_with_degeneracy(init, opts)?;
            let improves = cand.beads.len() > best.beads.len()
                && !cand.degeneracies.iter().any(|d| {
                    matches!(
                        d,
                        Degeneracy::CloseBeads { .. } | Degeneracy::Insignificant { .. }
                    )
                })
                && match opts.criterion {
                    GrowCriterion::Bic => cand.bic < best.bic,
                    GrowCriterion::RelDrop { min_drop } => cand.rss < (1.0 - min_drop) * best.rss,
                };
            history.push(GrowStep {
                n_beads: cand.beads.len(),
                rss: cand.rss,
                bic: cand.bic,
                accepted: improves,
            });
            if !improves {
                break;
            }
            best = cand;
        }
        best.history = history;
    }
    Ok(best)
}

/// Automatic initial guesses (the same the fit uses when `init` is not given): `n` beads by CLEAN
/// on the detection map ∂Sx/∂x + ∂Sy/∂y (or the one channel's sensitivity) with the given
/// stencil. Fewer than `n` are returned when the map has no further positive maximum.
pub fn detect_beads(
    sx: &Image,
    sy: &Image,
    tpl: &Template,
    channels: Channels,
    n: usize,
    stencil: Stencil,
) -> Result<Vec<BeadInit>> {
    check_range("n", n as f64, 1.0, 10_000.0)?;
    let d = detection_map(sx, sy, channels, stencil)?;
    Ok(clean(&d, tpl, channels, n, 0.0, 0.0))
}

/// The detection map: ∂Sx/∂x + ∂Sy/∂y (or the fitted channel's sensitivity).
pub(crate) fn detection_map(sx: &Image, sy: &Image, ch: Channels, st: Stencil) -> Result<Image> {
    let a = match ch {
        Channels::Sy => None,
        _ => Some(sensitivity(sx, Axis::X, st)?),
    };
    let b = match ch {
        Channels::Sx => None,
        _ => Some(sensitivity(sy, Axis::Y, st)?),
    };
    Ok(match (a, b) {
        (Some(a), Some(b)) => Image::new(&a.data + &b.data, a.x, a.y),
        (Some(a), None) => a,
        (None, Some(b)) => b,
        (None, None) => unreachable!(),
    })
}

/// The template's own detection response and its peak.
fn template_dmap_peak(tpl: &Template, ch: Channels) -> (f64, f64, f64) {
    let g = &tpl.grid;
    let f = |u: f64, v: f64| {
        let s = g.eval_grad(u, v);
        match ch {
            Channels::Both => s.du[0] + s.dv[1],
            Channels::Sx => s.du[0],
            Channels::Sy => s.dv[1],
        }
    };
    let mut best = (0.0, 0.0, f64::NEG_INFINITY);
    for j in 1..g.nv - 1 {
        for i in 1..g.nu - 1 {
            let (u, v) = (g.u0 + i as f64 * g.h, g.v0 + j as f64 * g.h);
            let d = f(u, v);
            if d > best.2 {
                best = (u, v, d);
            }
        }
    }
    let mut step = g.h / 4.0;
    for _ in 0..3 {
        let (cu, cv) = (best.0, best.1);
        for b in -4..=4 {
            for a in -4..=4 {
                let (u, v) = (cu + a as f64 * step, cv + b as f64 * step);
                let d = f(u, v);
                if d > best.2 {
                    best = (u, v, d);
                }
            }
        }
        step /= 4.0;
    }
    best
}

/// CLEAN: up to `n` beads from the detection map, stopping when the highest remaining maximum is
/// not above `min_peak` (instrument units of the map) or its bead would weigh no more than
/// `min_weight` (reference-bead units).
pub(crate) fn clean(
    d: &Image,
    tpl: &Template,
    ch: Channels,
    n: usize,
    min_peak: f64,
    min_weight: f64,
) -> Vec<BeadInit> {
    clean_peaks(d, tpl, ch, n, min_peak, min_weight)
        .into_iter()
        .map(|(b, _)| b)
        .collect()
}

/// As [`clean`], each bead with the height of its maximum in the detection map (the map's
/// units) when it was taken.
pub(crate) fn clean_peaks(
    d: &Image,
    tpl: &Template,
    ch: Channels,
    n: usize,
    min_peak: f64,
    min_weight: f64,
) -> Vec<(BeadInit, f64)> {
    let (pu, pv, d0) = template_dmap_peak(tpl, ch);
    if !(d0 > 0.0) {
        return vec![];
    }
    let mut work = d.data.clone();
    let (ax, ay) = (AxisMap::new(&d.x), AxisMap::new(&d.y));
    let ((u0, u1), (v0, v1)) = tpl.extent();
    let sub = |work: &mut Array2<f64>, b: &BeadInit| {
        for r in ay.range(b.y + v0, b.y + v1) {
            for c in ax.range(b.x + u0, b.x + u1) {
                let s = tpl.eval_grad(d.x[c] - b.x, d.y[r] - b.y);
                let t = match ch {
                    Channels::Both => s.du[0] + s.dv[1],
                    Channels::Sx => s.du[0],
                    Channels::Sy => s.dv[1],
                };
                work[[r, c]] -= b.weight * t / tpl.norm_factor;
            }
        }
    };
    let mut out = Vec::new();
    for _ in 0..n {
        let mut best: Option<(usize, usize, f64)> = None;
        for ((r, c), &v) in work.indexed_iter() {
            if v.is_finite() && best.is_none_or(|b| v > b.2) {
                best = Some((r, c, v));
            }
        }
        let Some((r, c, v)) = best else { break };
        if !(v > 0.0 && v > min_peak && v * tpl.norm_factor / d0 > min_weight) {
            break;
        }
        let para = |a: Option<f64>, b: f64, cc: Option<f64>| -> f64 {
            match (a, cc) {
                (Some(a), Some(cc)) if a.is_finite() && cc.is_finite() => {
                    let den = a - 2.0 * b + cc;
                    if den < 0.0 {
                        (0.5 * (a - cc) / den).clamp(-0.5, 0.5)
                    } else {
                        0.0
                    }
                }
                _ => 0.0,
            }
        };
        let (rows, cols) = work.dim();
        let fx = para(
            (c > 0).then(|| work[[r, c - 1]]),
            v,
            (c + 1 < cols).then(|| work[[r, c + 1]]),
        );
        let fy = para(
            (r > 0).then(|| work[[r - 1, c]]),
            v,
            (r + 1 < rows).then(|| work[[r + 1, c]]),
        );
        let x = d.x[c] + fx * ax.h - pu;
        let y = d.y[r] + fy * ay.h - pv;
        // Instrument units → reference-bead units: the bead's D peak is C·d0/norm_factor.
        let b = BeadInit {
            x,
            y,
            weight: v * tpl.norm_factor / d0,
        };
        sub(&mut work, &b);
        out.push((b, v));
    }
    out
}

/// The images prepared for fitting.
struct FitData<'a> {
    tpl: &'a Template,
    x: Vec<f64>,
    y: Vec<f64>,
    ax: AxisMap,
    ay: AxisMap,
    /// Row-major (rows, cols) data of the two channels; NaN = invalid.
    ch_data: [Vec<f64>; 2],
    chans: &'static [usize],
    m: usize,
    area: f64,
    w0: f64,
    min_sep: f64,
    /// 1/norm_factor: instrument units per reference-bead unit.
    inv_f: f64,
    /// Tile buffers reused from one evaluation to the next (one per tile in flight): no
    /// page-faulting allocation per evaluation. Taken from [`SCRATCH_POOL`] and given back on
    /// drop, so that the next fit does not allocate them again either.
    scratch: std::sync::Mutex<Vec<Scratch>>,
    /// 1 where the channel is fitted and its datum valid, else 0 (row-major, per channel).
    mask: [Vec<f64>; 2],
    /// The template's node values for the separable stencil (None for a linear or degenerate
    /// grid: those are sampled with `eval_grad`).
    planes: Option<TplPlanes>,
    /// Tests only: accumulate with the pixel-major reference.
    #[cfg(test)]
    reference: bool,
}

/// A tile's reused buffers: the windows' samples and the two residual images of the tile.
type Scratch = (Vec<f64>, [Vec<f64>; 2]);

/// The tiles of [`FitData::accumulate`]: rows × columns of pixels. A tile's windows (six planes
/// of ≲ 32 × 32 samples for each bead that reaches it) stay in a core's L2 cache.
const TILE_ROWS: usize = 32;
const TILE_COLS: usize = 128;

/// A bead that reaches a tile: its index and its window's rows and columns cut to the tile.
type TileItem = (usize, std::ops::Range<usize>, std::ops::Range<usize>);

/// Pixel ranges of a window.
type Shape = (std::ops::Range<usize>, std::ops::Range<usize>);

/// The tiles (rows × columns) covering an image of ny × nx pixels, row-major.
fn tiles(ny: usize, nx: usize) -> Vec<Shape> {
    (0..ny)
        .step_by(TILE_ROWS)
        .flat_map(|r0| {
            (0..nx)
                .step_by(TILE_COLS)
                .map(move |c0| (r0..(r0 + TILE_ROWS).min(ny), c0..(c0 + TILE_COLS).min(nx)))
        })
        .collect()
}

/// The beads whose windows (`shapes`) reach the tile `tr` × `tc`, in index order, with their
/// windows cut to the tile.
fn tile_items(
    shapes: &[Shape],
    tr: &std::ops::Range<usize>,
    tc: &std::ops::Range<usize>,
) -> Vec<TileItem> {
    let cut = |a: &std::ops::Range<usize>, b: &std::ops::Range<usize>| {
        a.start.max(b.start)..a.end.min(b.end).max(a.start.max(b.start))
    };
    shapes
        .iter()
        .enumerate()
        .filter_map(|(i, (rows, cols))| {
            let (r, c) = (cut(rows, tr), cut(cols, tc));
            (!r.is_empty() && !c.is_empty()).then_some((i, r, c))
        })
        .collect()
}

/// A tile's part of the sums (see [`FitData::tile_sums`]).
#[derive(Default)]
struct TileSums {
    rss: f64,
    /// (bead, Σ Jₓ·J_y, Σ Jₓ·e), unscaled.
    own: Vec<(usize, [[f64; 3]; 3], [f64; 3])>,
    /// (bead i, bead j > i, Σ Jᵢₓ·Jⱼ_y), unscaled.
    pairs: Vec<(usize, usize, [[f64; 3]; 3])>,
}

/// The tile buffers of the last fit, for the next one (allocating and zeroing a 40-bead fit's
/// buffers every fit was ~10 % of it). Kept only while they hold at most [`SCRATCH_KEEP`]
/// values.
static SCRATCH_POOL: std::sync::Mutex<Vec<Scratch>> = std::sync::Mutex::new(Vec::new());
const SCRATCH_KEEP: usize = 1 << 24;

impl Drop for FitData<'_> {
    fn drop(&mut self) {
        let s = std::mem::take(
            self.scratch
                .get_mut()
                .unwrap_or_else(std::sync::PoisonError::into_inner),
        );
        let held: usize = s
            .iter()
            .map(|(b, r)| b.capacity() + r[0].capacity() + r[1].capacity())
            .sum();
        if held <= SCRATCH_KEEP {
            *SCRATCH_POOL
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner) = s;
        }
    }
}

impl<'a> FitData<'a> {
    fn new(sx: &Image, sy: &Image, tpl: &'a Template, opts: &FitOptions) -> Result<Self> {
        if sx.data.dim() != sy.data.dim() || sx.x != sy.x || sx.y != sy.y {
            return Err(AnalysisError::BadInput {
                name: "sy",
                reason: "Sx and Sy images must have the same shape and axes".into(),
            });
        }
        if sx.rows() == 0 || sx.cols() == 0 {
            return Err(AnalysisError::BadInput {
                name: "sx",
                reason: "empty image".into(),
            });
        }
        check_axis("sx.x", &sx.x, 1)?;
        check_axis("sx.y", &sx.y, 1)?;
        let tr = tpl.truncation();
        if tr > opts.max_truncation {
            let ((u0, u1), (v0, v1)) = tpl.extent();
            return Err(AnalysisError::TemplateCoverage(format!(
                "the template is truncated: its border value is {:.1}% of its peak (allowed {:.1}%); it covers only u ∈ [{u0}, {u1}], v ∈ [{v0}, {v1}] µm, build it wider",
                100.0 * tr,
                100.0 * opts.max_truncation
            )));
        }
        let ch_data = [
            sx.data.iter().copied().collect::<Vec<_>>(),
            sy.data.iter().copied().collect::<Vec<_>>(),
        ];
        let chans = opts.channels.list();
        let m: usize = chans
            .iter()
            .map(|&c| ch_data[c].iter().filter(|v| v.is_finite()).count())
            .sum();
        if m == 0 {
            return Err(AnalysisError::BadInput {
                name: "sx, sy",
                reason: "no finite pixel in the fitted channels".into(),
            });
        }
        let (ax, ay) = (AxisMap::new(&sx.x), AxisMap::new(&sy.y));
        let (px, py) = (ax.h.abs(), ay.h.abs());
        let (px, py) = (
            if px > 0.0 { px } else { py },
            if py > 0.0 { py } else { px },
        );
        let (px, py) = if px > 0.0 {
            (px, py)
        } else {
            (tpl.grid.h, tpl.grid.h)
        };
        let area = sx.cols() as f64 * px * sx.rows() as f64 * py;
        let mask = [0, 1].map(|ch| {
            let on = chans.contains(&ch);
            ch_data[ch]
                .iter()
                .map(|v| if on && v.is_finite() { 1.0 } else { 0.0 })
                .collect::<Vec<f64>>()
        });
        let g = &tpl.grid;
        let planes = (g.interp == crate::optics::grid::Interp::Cubic && g.nu >= 2 && g.nv >= 2)
            .then(|| TplPlanes::new(g));
        Ok(Self {
            tpl,
            x: sx.x.clone(),
            y: sx.y.clone(),
            ax,
            ay,
            ch_data,
            chans,
            m,
            area,
            w0: opts.w0_um,
            min_sep: opts.min_separation * opts.w0_um,
            inv_f: 1.0 / tpl.norm_factor,
            scratch: std::sync::Mutex::new(std::mem::take(
                &mut *SCRATCH_POOL
                    .lock()
                    .unwrap_or_else(std::sync::PoisonError::into_inner),
            )),
            mask,
            planes,
            #[cfg(test)]
            reference: false,
        })
    }

    fn nx(&self) -> usize {
        self.x.len()
    }

    /// Error when the image cannot support `n` beads.
    fn check_count(&self, n: usize) -> Result<()> {
        let patch = (self.min_sep.max(0.25 * self.w0)).powi(2);
        let by_area = (self.area / patch).floor() as usize;
        let by_data = self.m.saturating_sub(1) / 3;
        let nmax = by_area.min(by_data);
        if n > nmax {
            return Err(AnalysisError::TooManyBeads(format!(
                "n = {n} beads but this image supports at most {nmax} (area {:.3} µm² / ({:.3} µm)² per bead = {by_area}; {} residuals allow {by_data} beads of 3 parameters)",
                self.area,
                patch.sqrt(),
                self.m
            )));
        }
        Ok(())
    }

    /// True when a bead at (x, y) has template support overlapping the image.
    fn reaches(&self, x: f64, y: f64) -> bool {
        let ((u0, u1), (v0, v1)) = self.tpl.extent();
        !self.ax.range(x + u0, x + u1).is_empty() && !self.ay.range(y + v0, y + v1).is_empty()
    }

    /// Each bead's window at parameters p = [C, x, y]ᵢ: the pixel rows and columns within the
    /// template's extent around it.
    fn windows(&self, p: &[f64]) -> Vec<Shape> {
        let ((u0, u1), (v0, v1)) = self.tpl.extent();
        p.chunks(3)
            .map(|b| {
                (
                    self.ay.range(b[2] + v0, b[2] + v1),
                    self.ax.range(b[1] + u0, b[1] + u1),
                )
            })
            .collect()
    }

    /// Adds the model of a tile's windows (`items`, `wins`; see [`FitData::sample_tile`]) to
    /// `out`, the tile's images of the channels `chans` (tw columns), beads in index order at
    /// every pixel; beads of weight zero add nothing.
    fn add_model(
        &self,
        p: &[f64],
        items: &[TileItem],
        wins: &[Window],
        chans: &[usize],
        tw: usize,
        out: &mut [Vec<f64>; 2],
    ) {
        for ((i, _, _), w) in items.iter().zip(wins) {
            let wi = p[3 * i] * self.inv_f;
            if wi == 0.0 {
                continue;
            }
            let nc = w.cols.len();
            for &ch in chans {
                let plane = w.plane(3 * ch);
                for (rr, r) in w.rows.clone().enumerate() {
                    let base = r * tw + w.cols.start;
                    let m = &mut out[ch][base..base + nc];
                    for (m, s) in m.iter_mut().zip(&plane[rr * nc..(rr + 1) * nc]) {
                        *m += wi * s;
                    }
                }
            }
        }
    }

    /// Accumulate RSS, JᵀJ and Jᵀr at parameters p = [C, x, y]ᵢ.
    ///
    /// Tile by tile and block-sparse ([`FitData::tile_sums`], tiles of [`TILE_ROWS`] ×
    /// [`TILE_COLS`] pixels, in parallel). In each tile, the window of every bead that reaches it
    /// (the pixels within the template's extent, cut to the tile) is sampled into six contiguous
    /// planes — Sx, ∂Sx/∂u, ∂Sx/∂v, Sy, ∂Sy/∂u, ∂Sy/∂v, each zero where that channel's datum is
    /// invalid or the channel is not fitted — by a separable Keys cubic ([`TplPlanes`],
    /// [`kernels`]): per window row the four-tap v-stencil over the template columns the window
    /// reaches, then per pixel the four-tap u-stencil. The tile's model is the sum of its windows
    /// in bead order; its share of JᵀJ comes block by block: a bead's own 3 × 3 block and its Jᵀr,
    /// and a pair's off-diagonal block only where the two windows overlap (beads whose windows
    /// never overlap do not couple: their block is zero), all as dot products over contiguous
    /// rows with four accumulators. The tiles' parts are summed in tile order (the same result
    /// for any number of threads). The work is O(beads × window pixels + overlaps). The sums run
    /// in another order than the pixel-major reference, so the results agree with it to rounding
    /// (≲ 1e-13 relative, tested), not bit for bit.
    fn accumulate(&self, p: &[f64]) -> (f64, DMatrix<f64>, DVector<f64>) {
        #[cfg(test)]
        if self.reference {
            return self.accumulate_reference(p, true);
        }
        use rayon::prelude::*;
        let nb = p.len() / 3;
        let np = p.len();
        let nx = self.nx();
        let shapes = self.windows(p);
        let ny = self.y.len();
        let outs: Vec<TileSums> = tiles(ny, nx)
            .par_iter()
            .map(|(tr, tc)| {
                let mut sc = self.scratch_take();
                let out = self.tile_sums(p, &shapes, tr.clone(), tc.clone(), &mut sc);
                self.scratch_give(sc);
                out
            })
            .collect();
        // Sum the tiles' parts in tile order (the same result for any number of threads).
        let mut rss = 0.0;
        let mut own = vec![([[0.0; 3]; 3], [0.0; 3]); nb];
        let mut pairs: std::collections::BTreeMap<(usize, usize), [[f64; 3]; 3]> =
            Default::default();
        for t in &outs {
            rss += t.rss;
            for &(i, a, g) in &t.own {
                let (oa, og) = &mut own[i];
                for x in 0..3 {
                    og[x] += g[x];
                    for y in 0..3 {
                        oa[x][y] += a[x][y];
                    }
                }
            }
            for &(i, j, b) in &t.pairs {
                let o = pairs.entry((i, j)).or_insert([[0.0; 3]; 3]);
                for x in 0..3 {
                    for y in 0..3 {
                        o[x][y] += b[x][y];
                    }
                }
            }
        }
        let inv_f = self.inv_f;
        // Scale of bead i's Jacobian columns relative to the planes: ∂r/∂C = S/f, ∂r/∂x = −C/f ∂S/∂u,
        // ∂r/∂y = −C/f ∂S/∂v.
        let scale = |i: usize| -> [f64; 3] {
            let w = p[3 * i] * inv_f;
            [inv_f, -w, -w]
        };
        let mut jtj = DMatrix::<f64>::zeros(np, np);
        let mut jtr = DVector::<f64>::zeros(np);
        for (i, (a, g)) in own.iter().enumerate() {
            let f = scale(i);
            for x in 0..3 {
                jtr[3 * i + x] = g[x] * f[x];
                for y in 0..3 {
                    jtj[(3 * i + x, 3 * i + y)] = a[x][y] * (f[x] * f[y]);
                }
            }
        }
        for (&(i, j), blk) in &pairs {
            let (fa, fb) = (scale(i), scale(j));
            for x in 0..3 {
                for y in 0..3 {
                    let v = blk[x][y] * (fa[x] * fb[y]);
                    jtj[(3 * i + x, 3 * j + y)] = v;
                    jtj[(3 * j + y, 3 * i + x)] = v;
                }
            }
        }
        (rss, jtj, jtr)
    }

    /// A tile buffer from the fit's pool (or a new one).
    fn scratch_take(&self) -> Scratch {
        self.scratch
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .pop()
            .unwrap_or_default()
    }

    /// Back to the pool.
    fn scratch_give(&self, sc: Scratch) {
        self.scratch
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .push(sc);
    }

    /// One tile's part of [`FitData::accumulate`]: the windows of the beads that reach the tile
    /// (rows `tr` × columns `tc` of the image) sampled over the tile only, the model and the
    /// residuals there, and the tile's share of the RSS, of each bead's own block and Jᵀr, and
    /// of each overlapping pair's block (unscaled). Everything a tile touches stays in the
    /// core's cache.
    fn tile_sums(
        &self,
        p: &[f64],
        shapes: &[Shape],
        tr: std::ops::Range<usize>,
        tc: std::ops::Range<usize>,
        sc: &mut Scratch,
    ) -> TileSums {
        let nx = self.nx();
        let (th, tw) = (tr.len(), tc.len());
        let items = tile_items(shapes, &tr, &tc);
        let mut out = TileSums::default();
        if items.is_empty() {
            // No bead: the residual is minus the data.
            for &ch in self.chans {
                for r in tr.clone() {
                    let k0 = r * nx + tc.start;
                    for (d, mk) in self.ch_data[ch][k0..k0 + tw]
                        .iter()
                        .zip(&self.mask[ch][k0..k0 + tw])
                    {
                        if *mk != 0.0 {
                            out.rss += d * d;
                        }
                    }
                }
            }
            return out;
        }
        let (buf, res) = sc;
        let wins = self.sample_tile(p, &items, &tr, &tc, Some(&self.mask), buf);
        // Model (beads in index order at every pixel), then residuals: model − data where the
        // datum is valid and the channel fitted, 0 elsewhere.
        for r in res.iter_mut() {
            r.clear();
            r.resize(th * tw, 0.0);
        }
        self.add_model(p, &items, &wins, self.chans, tw, res);
        for &ch in self.chans {
            let mut acc = [0.0; 4];
            for r in 0..th {
                let k0 = (tr.start + r) * nx + tc.start;
                let e = &mut res[ch][r * tw..(r + 1) * tw];
                let (d, mk) = (&self.ch_data[ch][k0..k0 + tw], &self.mask[ch][k0..k0 + tw]);
                for (k, ((e, d), mk)) in e.iter_mut().zip(d).zip(mk).enumerate() {
                    let v = if *mk != 0.0 { *e - d } else { 0.0 };
                    *e = v;
                    acc[k & 3] += v * v;
                }
            }
            out.rss += (acc[0] + acc[1]) + (acc[2] + acc[3]);
        }
        for ((i, _, _), w) in items.iter().zip(&wins) {
            let (a, g) = w.own_sums(res, self.chans, tw);
            out.own.push((*i, a, g));
        }
        for (x, (i, _, _)) in items.iter().enumerate() {
            for (y, (j, _, _)) in items.iter().enumerate().skip(x + 1) {
                let (a, b) = (&wins[x], &wins[y]);
                if a.rows.start.max(b.rows.start) < a.rows.end.min(b.rows.end)
                    && a.cols.start.max(b.cols.start) < a.cols.end.min(b.cols.end)
                {
                    out.pairs
                        .push((*i, *j, Window::pair_sums(a, b, self.chans)));
                }
            }
        }
        out
    }

    /// The windows of `items` (see [`tile_items`]) sampled into `buf`, with rows and columns
    /// relative to the tile's first pixel.
    fn sample_tile<'b>(
        &self,
        p: &[f64],
        items: &[TileItem],
        tr: &std::ops::Range<usize>,
        tc: &std::ops::Range<usize>,
        mask: Option<&[Vec<f64>; 2]>,
        buf: &'b mut Vec<f64>,
    ) -> Vec<Window<'b>> {
        let total: usize = items.iter().map(|(_, r, c)| r.len() * c.len()).sum();
        // Every element is written by `sample_window`.
        buf.resize(6 * total, 0.0);
        let mut wins: Vec<Window> = Vec::with_capacity(items.len());
        let mut rest = &mut buf[..6 * total];
        for (i, rows, cols) in items {
            let (s, b) = rest.split_at_mut(6 * rows.len() * cols.len());
            rest = b;
            self.sample_window(
                p[3 * i + 1],
                p[3 * i + 2],
                rows.clone(),
                cols.clone(),
                mask,
                s,
            );
            wins.push(Window {
                rows: rows.start - tr.start..rows.end - tr.start,
                cols: cols.start - tc.start..cols.end - tc.start,
                s,
            });
        }
        wins
    }

    /// Samples of the template around a bead at (bx, by) µm over the window `rows` × `cols`
    /// into `out`: six planes of rows.len() × cols.len() (see [`FitData::accumulate`]), zero
    /// where `mask` is 0 (the fit's mask: the channel's datum invalid or the channel not
    /// fitted; None: nowhere). Every element of `out` is written. Derivatives in
    /// instrument units per µm, as [`Grid2::eval_grad`](crate::optics::grid::Grid2::eval_grad).
    ///
    /// On x86-64 CPUs with AVX2 the same code runs compiled for AVX2 + FMA (runtime dispatch;
    /// the binary still runs on any x86-64 and other targets). No multiply–add is contracted
    /// into an FMA (Rust does not contract without `mul_add`), so both paths round alike.
    #[allow(clippy::too_many_arguments)]
    fn sample_window(
        &self,
        bx: f64,
        by: f64,
        rows: std::ops::Range<usize>,
        cols: std::ops::Range<usize>,
        mask: Option<&[Vec<f64>; 2]>,
        out: &mut [f64],
    ) {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
        {
            // SAFETY: the CPU supports the features the function is compiled for (checked just
            // above).
            unsafe { self.sample_window_avx2(bx, by, rows, cols, mask, out) };
            return;
        }
        self.sample_window_impl::<false>(bx, by, rows, cols, mask, out)
    }

    /// [`FitData::sample_window`] compiled for AVX2 + FMA.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    fn sample_window_avx2(
        &self,
        bx: f64,
        by: f64,
        rows: std::ops::Range<usize>,
        cols: std::ops::Range<usize>,
        mask: Option<&[Vec<f64>; 2]>,
        out: &mut [f64],
    ) {
        self.sample_window_impl::<true>(bx, by, rows, cols, mask, out)
    }

    /// `SIMD`: use the AVX2 kernels (only from [`FitData::sample_window_avx2`]).
    #[inline(always)]
    fn sample_window_impl<const SIMD: bool>(
        &self,
        bx: f64,
        by: f64,
        rows: std::ops::Range<usize>,
        cols: std::ops::Range<usize>,
        mask: Option<&[Vec<f64>; 2]>,
        out: &mut [f64],
    ) {
        let grid = &self.tpl.grid;
        let nc = cols.len();
        let npix = rows.len() * nc;
        if npix == 0 {
            // a bead whose window lies wholly outside the image (a fit can walk one there)
            return;
        }
        let nx = self.nx();
        let su: Option<Vec<GradStencil>> = match &self.planes {
            Some(_) => cols
                .clone()
                .map(|c| grid.grad_stencil_u(self.x[c] - bx))
                .collect(),
            None => None,
        };
        match (&self.planes, su) {
            (Some(tp), Some(su)) => {
                // Template columns the window reaches (stencil starts ≥ −1).
                let lo = su
                    .iter()
                    .filter(|s| s.inside)
                    .map(|s| s.first)
                    .min()
                    .unwrap_or(0);
                let hi = su
                    .iter()
                    .filter(|s| s.inside)
                    .map(|s| s.first + 4)
                    .max()
                    .unwrap_or(0);
                let width = (hi - lo).max(0) as usize;
                // Per window column: where its four taps start in the row buffer, and the Keys
                // weights and their derivatives; a column outside the template reads the first
                // taps with zero weights (its samples are zero, as `eval_grad`'s).
                let cols_st: Vec<(usize, [f64; 4], [f64; 4])> = su
                    .iter()
                    .map(|s| {
                        if s.inside {
                            ((s.first - lo) as usize, s.w, s.d)
                        } else {
                            (0, [0.0; 4], [0.0; 4])
                        }
                    })
                    .collect();
                // One window row's v-interpolated template columns, both channels and the
                // v-derivative together: node k = [Sx, Sy, ∂Sx/∂v·h, ∂Sy/∂v·h].
                let mut vrow = vec![[0.0f64; 4]; width];
                let ones = if mask.is_none() {
                    vec![1.0; nc]
                } else {
                    Vec::new()
                };
                let inv_h = 1.0 / grid.h;
                for (rr, r) in rows.enumerate() {
                    let sv = grid.grad_stencil_v(self.y[r] - by);
                    let sv = match sv {
                        Some(s) if s.inside && width > 0 => s,
                        _ => {
                            for pl in out.chunks_exact_mut(npix) {
                                pl[rr * nc..(rr + 1) * nc].fill(0.0);
                            }
                            continue;
                        }
                    };
                    let taps = [0, 1, 2, 3].map(|b| tp.row(sv.first + b as isize, lo, width));
                    if taps.iter().any(|t| t.len() != width) {
                        // Outside the padded grid (cannot happen for `grad_stencil_*`'s stencils).
                        for pl in out.chunks_exact_mut(npix) {
                            pl[rr * nc..(rr + 1) * nc].fill(0.0);
                        }
                        continue;
                    }
                    #[cfg(target_arch = "x86_64")]
                    if SIMD {
                        // SAFETY: SIMD is true only in `sample_window_avx2`, called after the
                        // CPU was found to support AVX2 and FMA.
                        unsafe { kernels::v_pass_avx2(&mut vrow, taps, &sv.w, &sv.d) };
                    } else {
                        kernels::v_pass(&mut vrow, taps, &sv.w, &sv.d);
                    }
                    #[cfg(not(target_arch = "x86_64"))]
                    kernels::v_pass(&mut vrow, taps, &sv.w, &sv.d);
                    let at = rr * nc;
                    let k0 = r * nx + cols.start;
                    let (m0, m1) = match mask {
                        Some(m) => (&m[0][k0..k0 + nc], &m[1][k0..k0 + nc]),
                        None => (&ones[..], &ones[..]),
                    };
                    let (o0, rest) = out.split_at_mut(npix);
                    let (o1, rest) = rest.split_at_mut(npix);
                    let (o2, rest) = rest.split_at_mut(npix);
                    let (o3, rest) = rest.split_at_mut(npix);
                    let (o4, o5) = rest.split_at_mut(npix);
                    let [o0, o1, o2, o3, o4, o5] =
                        [o0, o1, o2, o3, o4, o5].map(|pl| &mut pl[at..at + nc]);
                    let o = [o0, o1, o2, o3, o4, o5];
                    #[cfg(target_arch = "x86_64")]
                    if SIMD {
                        // SAFETY: as for the v pass.
                        unsafe { kernels::u_pass_avx2(o, &vrow, &cols_st, [m0, m1], inv_h) };
                    } else {
                        kernels::u_pass(o, &vrow, &cols_st, [m0, m1], inv_h);
                    }
                    #[cfg(not(target_arch = "x86_64"))]
                    kernels::u_pass(o, &vrow, &cols_st, [m0, m1], inv_h);
                }
            }
            _ => {
                for (rr, r) in rows.enumerate() {
                    let v = self.y[r] - by;
                    for (cc, c) in cols.clone().enumerate() {
                        let k = r * nx + c;
                        let e = grid.eval_grad(self.x[c] - bx, v);
                        let at = rr * nc + cc;
                        for ch in 0..2 {
                            let on = mask.is_none_or(|m| m[ch][k] != 0.0);
                            let z = |v: f64| if on { v } else { 0.0 };
                            out[3 * ch * npix + at] = z(e.v[ch]);
                            out[(3 * ch + 1) * npix + at] = z(e.du[ch]);
                            out[(3 * ch + 2) * npix + at] = z(e.dv[ch]);
                        }
                    }
                }
            }
        }
    }

    /// The pixel-major accumulation used before issue 20 (one `eval_grad` per bead and pixel,
    /// JᵀJ filled pixel by pixel), kept as the reference that [`FitData::accumulate`] must
    /// reproduce bit for bit.
    #[cfg(test)]
    fn accumulate_reference(
        &self,
        p: &[f64],
        want_normal: bool,
    ) -> (f64, DMatrix<f64>, DVector<f64>) {
        let nb = p.len() / 3;
        let np = p.len();
        let mut jtj = DMatrix::<f64>::zeros(
            if want_normal { np } else { 0 },
            if want_normal { np } else { 0 },
        );
        let mut jtr = DVector::<f64>::zeros(if want_normal { np } else { 0 });
        let ((u0, u1), (v0, v1)) = self.tpl.extent();
        let cr: Vec<std::ops::Range<usize>> = (0..nb)
            .map(|i| self.ax.range(p[3 * i + 1] + u0, p[3 * i + 1] + u1))
            .collect();
        let rr: Vec<std::ops::Range<usize>> = (0..nb)
            .map(|i| self.ay.range(p[3 * i + 2] + v0, p[3 * i + 2] + v1))
            .collect();
        let nx = self.nx();
        let mut rss = 0.0;
        let mut act: Vec<(usize, f64, crate::optics::grid::Sample)> = Vec::with_capacity(nb);
        let mut g = vec![0.0f64; np];
        let mut gi: Vec<usize> = Vec::with_capacity(np);
        let mut row_beads: Vec<usize> = Vec::with_capacity(nb);
        // Local 3k×3k accumulation: for each pixel the active parameter list is short.
        for r in 0..self.y.len() {
            row_beads.clear();
            row_beads.extend((0..nb).filter(|&i| rr[i].contains(&r)));
            let yv = self.y[r];
            for c in 0..nx {
                let k = r * nx + c;
                let valid: [bool; 2] = [
                    self.ch_data[0][k].is_finite(),
                    self.ch_data[1][k].is_finite(),
                ];
                if !self.chans.iter().any(|&ch| valid[ch]) {
                    continue;
                }
                act.clear();
                for &i in &row_beads {
                    if cr[i].contains(&c) {
                        let s = if want_normal {
                            self.tpl
                                .eval_grad(self.x[c] - p[3 * i + 1], yv - p[3 * i + 2])
                        } else {
                            crate::optics::grid::Sample {
                                v: self.tpl.eval(self.x[c] - p[3 * i + 1], yv - p[3 * i + 2]),
                                ..Default::default()
                            }
                        };
                        // Weights are in reference-bead units, the data in instrument units.
                        act.push((i, p[3 * i] * self.inv_f, s));
                    }
                }
                for &ch in self.chans {
                    if !valid[ch] {
                        continue;
                    }
                    let mut model = 0.0;
                    for &(_, w, s) in &act {
                        model += w * s.v[ch];
                    }
                    let res = model - self.ch_data[ch][k];
                    rss += res * res;
                    if want_normal && !act.is_empty() {
                        gi.clear();
                        for &(i, w, s) in &act {
                            g[3 * i] = s.v[ch] * self.inv_f;
                            g[3 * i + 1] = -w * s.du[ch];
                            g[3 * i + 2] = -w * s.dv[ch];
                            gi.extend_from_slice(&[3 * i, 3 * i + 1, 3 * i + 2]);
                        }
                        for (a, &ia) in gi.iter().enumerate() {
                            let ga = g[ia];
                            jtr[ia] += ga * res;
                            for &ib in &gi[a..] {
                                jtj[(ia, ib)] += ga * g[ib];
                            }
                        }
                    }
                }
            }
        }
        if want_normal {
            // Symmetrise (only pairs (ia ≤ ib in the per-pixel order) were filled).
            for a in 0..np {
                for b in a + 1..np {
                    let s = jtj[(a, b)] + jtj[(b, a)];
                    jtj[(a, b)] = s;
                    jtj[(b, a)] = s;
                }
            }
        }
        (rss, jtj, jtr)
    }

    /// Model images of Sx and Sy (all pixels, whatever was fitted) for beads p, sampled as in
    /// [`FitData::accumulate`] (the separable stencil; equal to
    /// [`Template::render`]'s to rounding).
    fn model(&self, p: &[f64]) -> [Array2<f64>; 2] {
        use rayon::prelude::*;
        let (ny, nx) = (self.y.len(), self.nx());
        if self.planes.is_none() {
            let [a, b, _] = self.tpl.render(
                &p.chunks(3)
                    .map(|b| (b[1], b[2], b[0] * self.inv_f))
                    .collect::<Vec<_>>(),
                &self.x,
                &self.y,
            );
            return [a, b];
        }
        let shapes = self.windows(p);
        // Tile by tile (as `accumulate`), each pixel the sum of the beads in index order.
        let tiles = tiles(ny, nx);
        let parts: Vec<[Vec<f64>; 2]> = tiles
            .par_iter()
            .map(|(tr, tc)| {
                let (th, tw) = (tr.len(), tc.len());
                let mut o = [vec![0.0; th * tw], vec![0.0; th * tw]];
                let items = tile_items(&shapes, tr, tc);
                if items.is_empty() {
                    return o;
                }
                let mut sc = self.scratch_take();
                let wins = self.sample_tile(p, &items, tr, tc, None, &mut sc.0);
                self.add_model(p, &items, &wins, &[0, 1], tw, &mut o);
                drop(wins);
                self.scratch_give(sc);
                o
            })
            .collect();
        let mut out = [Array2::zeros((ny, nx)), Array2::zeros((ny, nx))];
        for ((tr, tc), part) in tiles.iter().zip(&parts) {
            for (ch, o) in out.iter_mut().enumerate() {
                for (rr, r) in tr.clone().enumerate() {
                    for (cc, c) in tc.clone().enumerate() {
                        o[[r, c]] = part[ch][rr * tc.len() + cc];
                    }
                }
            }
        }
        out
    }

    /// One LM run from `init` (see [`levenberg_marquardt`]).
    fn run_lm(&self, init: &[BeadInit], opts: &FitOptions) -> Result<RawFit> {
        let x0: Vec<f64> = init.iter().flat_map(|b| [b.weight, b.x, b.y]).collect();
        let tol = Tolerances {
            ftol: opts.ftol,
            xtol: opts.xtol,
            gtol: opts.gtol,
            patience: opts.patience,
        };
        let raw = levenberg_marquardt(|p| self.accumulate(p), x0, &tol);
        if raw.p.iter().any(|v| !v.is_finite()) {
            return Err(AnalysisError::Failed(format!(
                "the optimiser returned non-finite parameters ({})",
                raw.reason
            )));
        }
        Ok(raw)
    }

    /// LM fit with all degeneracy checks (see the module docs).
    fn fit_with_degeneracy(&self, init: Vec<BeadInit>, opts: &FitOptions) -> Result<FitResult> {
        let mut res = self.fit_merge_close(init, opts, Vec::new())?;
        let lim = opts.resolve_separation * self.w0;
        'outer: while opts.merge_degenerate && lim > 0.0 && res.beads.len() > 1 {
            let b = &res.beads;
            let mut pairs: Vec<(usize, usize, f64)> = Vec::new();
            for i in 0..b.len() {
                for j in i + 1..b.len() {
                    let d = (b[i].x - b[j].x).hypot(b[i].y - b[j].y);
                    if d < lim {
                        pairs.push((i, j, d));
                    }
                }
            }
            pairs.sort_by(|a, b| a.2.total_cmp(&b.2));
            for (i, j, d) in pairs {
                let (a, c) = (b[i], b[j]);
                let mut init: Vec<BeadInit> = b
                    .iter()
                    .enumerate()
                    .filter(|(k, _)| *k != i && *k != j)
                    .map(|(_, x)| BeadInit {
                        x: x.x,
                        y: x.y,
                        weight: x.weight,
                    })
                    .collect();
                init.push(merge_pair(
                    BeadInit {
                        x: a.x,
                        y: a.y,
                        weight: a.weight,
                    },
                    BeadInit {
                        x: c.x,
                        y: c.y,
                        weight: c.weight,
                    },
                ));
                let mut deg = res.degeneracies.clone();
                let alt0 = self.fit_merge_close(init, opts, Vec::new())?;
                let insignificant = |x: &Bead| {
                    x.weight.abs() < 1e-9 || x.weight_err.is_some_and(|e| x.weight.abs() < 2.0 * e)
                };
                if alt0.bic <= res.bic || insignificant(&a) || insignificant(&c) {
                    deg.push(Degeneracy::Unresolved {
                        a: [a.x, a.y, a.weight],
                        b: [c.x, c.y, c.weight],
                        distance_um: d,
                        delta_bic: res.bic - alt0.bic,
                    });
                    deg.extend(alt0.degeneracies.iter().cloned());
                    let total = res.total_evaluations + alt0.total_evaluations;
                    res = alt0;
                    res.degeneracies = deg;
                    res.total_evaluations = total;
                    continue 'outer;
                }
            }
            break;
        }
        // Weights consistent with zero.
        let extra: Vec<Degeneracy> = res
            .beads
            .iter()
            .filter(|b| {
                b.weight.abs() < 1e-9 || b.weight_err.is_some_and(|e| b.weight.abs() < 2.0 * e)
            })
            .map(|b| Degeneracy::Insignificant {
                x: b.x,
                y: b.y,
                weight: b.weight,
                weight_err: b.weight_err,
            })
            .collect();
        res.degeneracies.extend(extra);
        Ok(res)
    }

    /// LM fit with merging of pairs closer than min_separation·w0 and dropping of beads out of
    /// reach, then the statistics.
    fn fit_merge_close(
        &self,
        init: Vec<BeadInit>,
        opts: &FitOptions,
        mut degeneracies: Vec<Degeneracy>,
    ) -> Result<FitResult> {
        let mut beads = init;
        let mut total_eval = 0;
        let mut raw;
        loop {
            raw = self.run_lm(&beads, opts)?;
            total_eval += raw.evaluations;
            let cur: Vec<BeadInit> = raw
                .p
                .chunks(3)
                .map(|b| BeadInit {
                    weight: b[0],
                    x: b[1],
                    y: b[2],
                })
                .collect();
            // Beads out of reach.
            let (keep, gone): (Vec<BeadInit>, Vec<BeadInit>) =
                cur.iter().partition(|b| self.reaches(b.x, b.y));
            if !gone.is_empty() && !keep.is_empty() {
                for b in &gone {
                    degeneracies.push(Degeneracy::BeadOutside {
                        x: b.x,
                        y: b.y,
                        weight: b.weight,
                    });
                }
                beads = keep;
                continue;
            }
            // Closest pair below the separation limit.
            let mut pair: Option<(usize, usize, f64)> = None;
            for i in 0..cur.len() {
                for j in i + 1..cur.len() {
                    let d = (cur[i].x - cur[j].x).hypot(cur[i].y - cur[j].y);
                    if d < self.min_sep && pair.is_none_or(|p| d < p.2) {
                        pair = Some((i, j, d));
                    }
                }
            }
            if let Some((i, j, d)) = pair {
                let (a, b) = (cur[i], cur[j]);
                degeneracies.push(Degeneracy::CloseBeads {
                    a: [a.x, a.y, a.weight],
                    b: [b.x, b.y, b.weight],
                    distance_um: d,
                    merged: opts.merge_degenerate,
                });
                if opts.merge_degenerate {
                    let merged = merge_pair(a, b);
                    let mut next: Vec<BeadInit> = cur
                        .iter()
                        .enumerate()
                        .filter(|(k, _)| *k != i && *k != j)
                        .map(|(_, b)| *b)
                        .collect();
                    next.push(merged);
                    beads = next;
                    continue;
                }
            }
            break;
        }
        // Statistics at the solution.
        let p = &raw.p;
        let nb = p.len() / 3;
        // The optimiser's last accepted evaluation is the one at the solution.
        let (rss, jtj) = (raw.rss, &raw.jtj);
        let np = p.len();
        let dof = self.m.saturating_sub(np);
        let (sigma, est) = match opts.sigma {
            Some(s) => (s, false),
            None => ((rss / dof.max(1) as f64).sqrt(), true),
        };
        let chi2 = if sigma > 0.0 {
            rss / (sigma * sigma)
        } else {
            0.0
        };
        let mf = self.m as f64;
        let bic = match opts.sigma {
            Some(_) => chi2 + np as f64 * mf.ln(),
            None => mf * (rss.max(1e-300) / mf).ln() + np as f64 * mf.ln(),
        };
        // The condition number and the covariance are independent O(n³) steps: computed side by
        // side (the covariance is dropped if the problem is ill-conditioned).
        let (condition, cov) = rayon::join(
            || scaled_condition(jtj),
            || {
                jtj.clone()
                    .cholesky()
                    .map(|c| c.inverse() * (sigma * sigma))
            },
        );
        let ill = !(condition <= opts.cond_limit);
        if ill {
            degeneracies.push(Degeneracy::IllConditioned { condition });
        }
        let cov = if ill { None } else { cov };
        let beads_out: Vec<Bead> = (0..nb)
            .map(|i| {
                let e = |k: usize| {
                    cov.as_ref()
                        .map(|c| c[(3 * i + k, 3 * i + k)].max(0.0).sqrt())
                };
                Bead {
                    weight: p[3 * i],
                    x: p[3 * i + 1],
                    y: p[3 * i + 2],
                    weight_err: e(0),
                    x_err: e(1),
                    y_err: e(2),
                }
            })
            .collect();
        let [msx, msy] = self.model(p);
        let shape = msx.dim();
        let dsx = Array2::from_shape_vec(shape, self.ch_data[0].clone()).expect("shape");
        let dsy = Array2::from_shape_vec(shape, self.ch_data[1].clone()).expect("shape");
        let img = |a: Array2<f64>| Image::new(a, self.x.clone(), self.y.clone());
        Ok(FitResult {
            beads: beads_out,
            residual_sx: img(&dsx - &msx),
            residual_sy: img(&dsy - &msy),
            model_sx: img(msx),
            model_sy: img(msy),
            rss,
            chi2,
            dof,
            n_residuals: self.m,
            sigma,
            sigma_estimated: est,
            bic,
            iterations: raw.iterations,
            evaluations: raw.evaluations,
            total_evaluations: total_eval,
            status: raw.status,
            reason: raw.reason,
            condition,
            degeneracies,
            history: vec![],
        })
    }
}

/// One bead's window (pixel rows and columns within the template's extent around it) and its
/// template samples there, row-major.
struct Window<'s> {
    rows: std::ops::Range<usize>,
    cols: std::ops::Range<usize>,
    /// Six planes of rows × cols samples (see [`FitData::accumulate`]).
    s: &'s [f64],
}

impl Window<'_> {
    /// Σ over the window of (Jₓ·J_y, Jₓ·e) for the three planes of each fitted channel
    /// (unscaled; see [`FitData::accumulate`]), e the residual images.
    fn own_sums(
        &self,
        res: &[Vec<f64>; 2],
        chans: &[usize],
        nx: usize,
    ) -> ([[f64; 3]; 3], [f64; 3]) {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
        {
            // SAFETY: the CPU supports the features the function is compiled for.
            return unsafe { self.own_sums_avx2(res, chans, nx) };
        }
        self.own_sums_impl(res, chans, nx)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    fn own_sums_avx2(
        &self,
        res: &[Vec<f64>; 2],
        chans: &[usize],
        nx: usize,
    ) -> ([[f64; 3]; 3], [f64; 3]) {
        self.own_sums_impl(res, chans, nx)
    }

    #[inline(always)]
    fn own_sums_impl(
        &self,
        res: &[Vec<f64>; 2],
        chans: &[usize],
        nx: usize,
    ) -> ([[f64; 3]; 3], [f64; 3]) {
        let nc = self.cols.len();
        let mut a = [[0.0; 3]; 3];
        let mut g = [0.0; 3];
        for &ch in chans {
            let pl = [
                self.plane(3 * ch),
                self.plane(3 * ch + 1),
                self.plane(3 * ch + 2),
            ];
            for (rr, r) in self.rows.clone().enumerate() {
                let base = r * nx + self.cols.start;
                let e = &res[ch][base..base + nc];
                let row = |k: usize| &pl[k][rr * nc..(rr + 1) * nc];
                let (aa, gg) = dot_sym([row(0), row(1), row(2)], e);
                for x in 0..3 {
                    g[x] += gg[x];
                    for y in 0..3 {
                        a[x][y] += aa[x][y];
                    }
                }
            }
        }
        (a, g)
    }

    /// Σ over the overlap of windows a and b of aₓ·b_y for the three planes of each fitted
    /// channel (unscaled).
    fn pair_sums(a: &Self, b: &Self, chans: &[usize]) -> [[f64; 3]; 3] {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
        {
            // SAFETY: the CPU supports the features the function is compiled for.
            return unsafe { Self::pair_sums_avx2(a, b, chans) };
        }
        Self::pair_sums_impl(a, b, chans)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    fn pair_sums_avx2(a: &Self, b: &Self, chans: &[usize]) -> [[f64; 3]; 3] {
        Self::pair_sums_impl(a, b, chans)
    }

    #[inline(always)]
    fn pair_sums_impl(a: &Self, b: &Self, chans: &[usize]) -> [[f64; 3]; 3] {
        let rows = a.rows.start.max(b.rows.start)..a.rows.end.min(b.rows.end);
        let cols = a.cols.start.max(b.cols.start)..a.cols.end.min(b.cols.end);
        let (nca, ncb) = (a.cols.len(), b.cols.len());
        let mut blk = [[0.0; 3]; 3];
        for &ch in chans {
            for r in rows.clone() {
                let oa = (r - a.rows.start) * nca + (cols.start - a.cols.start);
                let ob = (r - b.rows.start) * ncb + (cols.start - b.cols.start);
                let n = cols.len();
                let ra = [0, 1, 2].map(|k| &a.plane(3 * ch + k)[oa..oa + n]);
                let rb = [0, 1, 2].map(|k| &b.plane(3 * ch + k)[ob..ob + n]);
                let bb = dot_block(ra, rb);
                for x in 0..3 {
                    for y in 0..3 {
                        blk[x][y] += bb[x][y];
                    }
                }
            }
        }
        blk
    }

    /// Plane k: 3·channel + (0 value, 1 ∂/∂u, 2 ∂/∂v).
    fn plane(&self, k: usize) -> &[f64] {
        let n = self.s.len() / 6;
        &self.s[k * n..(k + 1) * n]
    }
}

/// The two passes of the separable window sampler ([`FitData::sample_window`]), each as portable
/// scalar code and as AVX2 intrinsics with the same operations in the same order per lane (no
/// fused multiply–add), so both give the same bits.
mod kernels {
    /// One window row's v pass: `vrow[k]` = Σ_b (w_b·T_b[k], d_b·T_b[k]) over the four template
    /// rows `taps` (nodes [Sx, Sy]), as [Σw·Sx, Σw·Sy, Σd·Sx, Σd·Sy].
    #[inline(always)]
    pub(super) fn v_pass(
        vrow: &mut [[f64; 4]],
        taps: [&[[f64; 2]]; 4],
        w: &[f64; 4],
        d: &[f64; 4],
    ) {
        for (k, acc) in vrow.iter_mut().enumerate() {
            let mut a = [0.0f64; 4];
            for b in 0..4 {
                let n = taps[b][k];
                a[0] += w[b] * n[0];
                a[1] += w[b] * n[1];
                a[2] += d[b] * n[0];
                a[3] += d[b] * n[1];
            }
            *acc = a;
        }
    }

    /// One window row's u pass: per column, its four taps of `vrow` from `off` weighted by the
    /// Keys weights w (values, ∂/∂v) and their derivatives d (∂/∂u), scaled by 1/h for the
    /// derivatives and by the channel's mask (0 or 1), into the six output rows
    /// [Sx, ∂Sx/∂u, ∂Sx/∂v, Sy, ∂Sy/∂u, ∂Sy/∂v].
    #[inline(always)]
    pub(super) fn u_pass(
        o: [&mut [f64]; 6],
        vrow: &[[f64; 4]],
        cols: &[(usize, [f64; 4], [f64; 4])],
        mask: [&[f64]; 2],
        inv_h: f64,
    ) {
        let [o0, o1, o2, o3, o4, o5] = o;
        for (cc, &(off, w, d)) in cols.iter().enumerate() {
            let t: &[[f64; 4]; 4] = vrow[off..off + 4].try_into().expect("4 taps");
            let mut a = [0.0f64; 4];
            let mut g = [0.0f64; 4];
            for b in 0..4 {
                for l in 0..4 {
                    a[l] += w[b] * t[b][l];
                    g[l] += d[b] * t[b][l];
                }
            }
            let (k0, k1) = (mask[0][cc], mask[1][cc]);
            o0[cc] = a[0] * k0;
            o1[cc] = g[0] * inv_h * k0;
            o2[cc] = a[2] * inv_h * k0;
            o3[cc] = a[1] * k1;
            o4[cc] = g[1] * inv_h * k1;
            o5[cc] = a[3] * inv_h * k1;
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    pub(super) unsafe fn v_pass_avx2(
        vrow: &mut [[f64; 4]],
        taps: [&[[f64; 2]]; 4],
        w: &[f64; 4],
        d: &[f64; 4],
    ) {
        use std::arch::x86_64::*;
        let n = vrow.len();
        assert!(taps.iter().all(|t| t.len() == n));
        let wd = [0, 1, 2, 3].map(|b| _mm256_setr_pd(w[b], w[b], d[b], d[b]));
        for k in 0..n {
            let mut a = _mm256_setzero_pd();
            for b in 0..4 {
                // SAFETY: k < n = taps[b].len(); a node is two f64 (16 bytes).
                let t = _mm256_broadcast_pd(&*(taps[b].as_ptr().add(k) as *const __m128d));
                a = _mm256_add_pd(a, _mm256_mul_pd(wd[b], t));
            }
            // SAFETY: k < n = vrow.len(); a row element is four f64 (32 bytes).
            _mm256_storeu_pd(vrow.as_mut_ptr().add(k) as *mut f64, a);
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    pub(super) unsafe fn u_pass_avx2(
        o: [&mut [f64]; 6],
        vrow: &[[f64; 4]],
        cols: &[(usize, [f64; 4], [f64; 4])],
        mask: [&[f64]; 2],
        inv_h: f64,
    ) {
        use std::arch::x86_64::*;
        let n = cols.len();
        assert!(o.iter().all(|r| r.len() == n) && mask.iter().all(|m| m.len() == n));
        assert!(cols.iter().all(|c| c.0 + 4 <= vrow.len()));
        let [o0, o1, o2, o3, o4, o5] = o;
        let sa = _mm256_setr_pd(1.0, 1.0, inv_h, inv_h);
        let sg = _mm256_set1_pd(inv_h);
        for (cc, &(off, w, d)) in cols.iter().enumerate() {
            let mut a = _mm256_setzero_pd();
            let mut g = _mm256_setzero_pd();
            for b in 0..4 {
                // SAFETY: off + 4 ≤ vrow.len() (asserted above).
                let t = _mm256_loadu_pd(vrow.as_ptr().add(off + b) as *const f64);
                a = _mm256_add_pd(a, _mm256_mul_pd(_mm256_set1_pd(w[b]), t));
                g = _mm256_add_pd(g, _mm256_mul_pd(_mm256_set1_pd(d[b]), t));
            }
            let (k0, k1) = (mask[0][cc], mask[1][cc]);
            let k = _mm256_setr_pd(k0, k1, k0, k1);
            let a = _mm256_mul_pd(_mm256_mul_pd(a, sa), k);
            let g = _mm256_mul_pd(_mm256_mul_pd(g, sg), k);
            let mut av = [0.0f64; 4];
            let mut gv = [0.0f64; 4];
            _mm256_storeu_pd(av.as_mut_ptr(), a);
            _mm256_storeu_pd(gv.as_mut_ptr(), g);
            o0[cc] = av[0];
            o1[cc] = gv[0];
            o2[cc] = av[2];
            o3[cc] = av[1];
            o4[cc] = gv[1];
            o5[cc] = av[3];
        }
    }
}

/// The template's Sx and Sy node values, interleaved per node ([Sx, Sy]) in row-major order,
/// padded with `PAD` zero nodes on every side so that a cubic stencil reaching one node past the
/// grid (as [`Grid2::grad_stencil_u`](crate::optics::grid::Grid2::grad_stencil_u) allows) reads
/// zeros without a bounds test.
struct TplPlanes {
    stride: usize,
    rows: usize,
    data: Vec<[f64; 2]>,
}

impl TplPlanes {
    const PAD: usize = 2;

    fn new(g: &crate::optics::grid::Grid2) -> Self {
        let stride = g.nu + 2 * Self::PAD;
        let rows = g.nv + 2 * Self::PAD;
        let mut data = vec![[0.0; 2]; stride * rows];
        for j in 0..g.nv {
            for i in 0..g.nu {
                let n = g.data[j * g.nu + i];
                data[(j + Self::PAD) * stride + i + Self::PAD] = [n[0], n[1]];
            }
        }
        Self { stride, rows, data }
    }

    /// Nodes `first..first + width` of node row `j` (indices may run up to `PAD` past the grid:
    /// zeros; beyond that the row is empty and reads as zeros).
    fn row(&self, j: isize, first: isize, width: usize) -> &[[f64; 2]] {
        let pad = Self::PAD as isize;
        let (jj, ii) = (j + pad, first + pad);
        if jj < 0 || jj as usize >= self.rows || ii < 0 || ii as usize + width > self.stride {
            // Outside the padded grid (cannot happen for the stencils of `grad_stencil_*`).
            return &[];
        }
        let at = jj as usize * self.stride + ii as usize;
        &self.data[at..at + width]
    }
}

/// Dot products of three rows `a` with three rows `b` (all of one length): Σ aₓ·b_y. Four
/// accumulators per sum (one 256-bit vector with AVX2).
#[inline(always)]
fn dot_block(a: [&[f64]; 3], b: [&[f64]; 3]) -> [[f64; 3]; 3] {
    const L: usize = 4;
    let n = a[0].len();
    let (a0, a1, a2) = (&a[0][..n], &a[1][..n], &a[2][..n]);
    let (b0, b1, b2) = (&b[0][..n], &b[1][..n], &b[2][..n]);
    let mut m = [[[0.0f64; L]; 3]; 3];
    let it = a0
        .chunks_exact(L)
        .zip(a1.chunks_exact(L))
        .zip(a2.chunks_exact(L))
        .zip(
            b0.chunks_exact(L)
                .zip(b1.chunks_exact(L))
                .zip(b2.chunks_exact(L)),
        );
    for (((x0, x1), x2), ((y0, y1), y2)) in it {
        let av = [x0, x1, x2];
        let bv = [y0, y1, y2];
        for x in 0..3 {
            for y in 0..3 {
                for l in 0..L {
                    m[x][y][l] += av[x][l] * bv[y][l];
                }
            }
        }
    }
    let mut out = [[0.0; 3]; 3];
    for x in 0..3 {
        for y in 0..3 {
            let s = &m[x][y];
            out[x][y] = (s[0] + s[1]) + (s[2] + s[3]);
            for l in n - n % L..n {
                out[x][y] += a[x][l] * b[y][l];
            }
        }
    }
    out
}

/// For one bead's rows a (value, ∂/∂u, ∂/∂v) and the residual row e: (Σ aₓ·a_y, Σ aₓ·e), with
/// four accumulators per sum.
#[inline(always)]
fn dot_sym(a: [&[f64]; 3], e: &[f64]) -> ([[f64; 3]; 3], [f64; 3]) {
    const L: usize = 4;
    let n = a[0].len();
    let (a0, a1, a2, e) = (&a[0][..n], &a[1][..n], &a[2][..n], &e[..n]);
    // Upper triangle 00 01 02 11 12 22, then the gradient.
    let mut m = [[0.0f64; L]; 6];
    let mut g = [[0.0f64; L]; 3];
    let it = a0
        .chunks_exact(L)
        .zip(a1.chunks_exact(L))
        .zip(a2.chunks_exact(L))
        .zip(e.chunks_exact(L));
    for (((x0, x1), x2), ee) in it {
        for l in 0..L {
            m[0][l] += x0[l] * x0[l];
            m[1][l] += x0[l] * x1[l];
            m[2][l] += x0[l] * x2[l];
            m[3][l] += x1[l] * x1[l];
            m[4][l] += x1[l] * x2[l];
            m[5][l] += x2[l] * x2[l];
            g[0][l] += x0[l] * ee[l];
            g[1][l] += x1[l] * ee[l];
            g[2][l] += x2[l] * ee[l];
        }
    }
    let sum = |s: &[f64; L]| (s[0] + s[1]) + (s[2] + s[3]);
    let mut t = m.map(|s| sum(&s));
    let mut go = g.map(|s| sum(&s));
    for l in n - n % L..n {
        t[0] += a0[l] * a0[l];
        t[1] += a0[l] * a1[l];
        t[2] += a0[l] * a2[l];
        t[3] += a1[l] * a1[l];
        t[4] += a1[l] * a2[l];
        t[5] += a2[l] * a2[l];
        go[0] += a0[l] * e[l];
        go[1] += a1[l] * e[l];
        go[2] += a2[l] * e[l];
    }
    (
        [[t[0], t[1], t[2]], [t[1], t[3], t[4]], [t[2], t[4], t[5]]],
        go,
    )
}

/// One bead replacing two: weights summed, position |C|-weighted.
fn merge_pair(a: BeadInit, b: BeadInit) -> BeadInit {
    let (wa, wb) = (a.weight.abs(), b.weight.abs());
    let s = wa + wb;
    if s > 0.0 {
        BeadInit {
            x: (wa * a.x + wb * b.x) / s,
            y: (wa * a.y + wb * b.y) / s,
            weight: a.weight + b.weight,
        }
    } else {
        BeadInit {
            x: 0.5 * (a.x + b.x),
            y: 0.5 * (a.y + b.y),
            weight: 0.0,
        }
    }
}

/// Full residual vector and Jacobian (one row per valid pixel and channel) — the uncompressed
/// problem, for tests and for users who want J itself. Rows ordered channel-major, then pixel
/// row-major.
pub fn full_jacobian(
    sx: &Image,
    sy: &Image,
    tpl: &Template,
    beads: &[BeadInit],
    channels: Channels,
) -> Result<(DVector<f64>, DMatrix<f64>)> {
    let opts = FitOptions {
        channels,
        max_truncation: 1.0,
        ..Default::default()
    };
    let d = FitData::new(sx, sy, tpl, &opts)?;
    let np = beads.len() * 3;
    let mut r = Vec::new();
    let mut rows: Vec<Vec<f64>> = Vec::new();
    let nx = d.nx();
    for &ch in d.chans {
        for k in 0..d.ch_data[ch].len() {
            let v = d.ch_data[ch][k];
            if !v.is_finite() {
                continue;
            }
            let (row, col) = (k / nx, k % nx);
            let mut model = 0.0;
            let mut jr = vec![0.0; np];
            for (i, b) in beads.iter().enumerate() {
                let s = tpl.eval_grad(d.x[col] - b.x, d.y[row] - b.y);
                let f = d.inv_f;
                model += b.weight * f * s.v[ch];
                jr[3 * i] = s.v[ch] * f;
                jr[3 * i + 1] = -b.weight * f * s.du[ch];
                jr[3 * i + 2] = -b.weight * f * s.dv[ch];
            }
            r.push(model - v);
            rows.push(jr);
        }
    }
    let m = r.len();
    Ok((
        DVector::from_vec(r),
        DMatrix::from_fn(m, np, |i, j| rows[i][j]),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn compressed_problem_matches_full_normal_equations() {
        let tpl = Template::analytic_standin(0.4, 0.02, 1.6).unwrap();
        let x: Vec<f64> = (0..40).map(|i| i as f64 * 0.05).collect();
        let truth = [(0.8, 0.9, 1.0), (1.2, 1.1, 2.0)];
        let [sx, sy, _] = tpl.render(&truth, &x, &x);
        let mut sx = Image::new(sx, x.clone(), x.clone());
        sx.data[[3, 4]] = f64::NAN;
        let sy = Image::new(sy, x.clone(), x.clone());
        let guess = [
            BeadInit {
                x: 0.82,
                y: 0.88,
                weight: 1.1,
            },
            BeadInit {
                x: 1.18,
                y: 1.13,
                weight: 1.8,
            },
        ];
        let (r, j) = full_jacobian(&sx, &sy, &tpl, &guess, Channels::Both).unwrap();
        let d = FitData::new(&sx, &sy, &tpl, &FitOptions::default()).unwrap();
        let p: Vec<f64> = guess.iter().flat_map(|b| [b.weight, b.x, b.y]).collect();
        let (rss, jtj, jtr) = d.accumulate(&p);
        assert!((rss - r.norm_squared()).abs() < 1e-10 * rss);
        let jtj_full = j.transpose() * &j;
        let jtr_full = j.transpose() * &r;
        assert!((jtj - &jtj_full).amax() < 1e-9 * jtj_full.amax());
        assert!((jtr - &jtr_full).amax() < 1e-9 * jtr_full.amax());
        // Analytic Jacobian vs central differences of the residuals.
        let h = 1e-6;
        for k in 0..6 {
            let mut gp = guess;
            let mut gm = guess;
            let (bi, pi) = (k / 3, k % 3);
            let bump = |b: &mut BeadInit, s: f64| match pi {
                0 => b.weight += s,
                1 => b.x += s,
                _ => b.y += s,
            };
            bump(&mut gp[bi], h);
            bump(&mut gm[bi], -h);
            let (rp, _) = full_jacobian(&sx, &sy, &tpl, &gp, Channels::Both).unwrap();
            let (rm, _) = full_jacobian(&sx, &sy, &tpl, &gm, Channels::Both).unwrap();
            let fd = (rp - rm) / (2.0 * h);
            assert!((fd - j.column(k)).amax() < 1e-6, "column {k}");
        }
    }

    /// A scene for the accumulation tests: 7 beads, two overlapping pairs, one half outside
    /// the image, a NaN pixel per channel and one pixel with both channels NaN, noise.
    fn scene(tpl: &Template) -> (Image, Image, Vec<BeadInit>) {
        let x: Vec<f64> = (0..48).map(|i| 0.1 + i as f64 * 0.05).collect();
        let y: Vec<f64> = (0..44).map(|i| -0.2 + i as f64 * 0.05).collect();
        let truth = [
            (0.5, 0.3, 1.0),
            (0.72, 0.41, 0.7),
            (1.6, 1.5, 1.3),
            (1.9, 1.45, -0.4),
            (2.4, 0.2, 0.9),
            (0.05, 1.9, 1.1),
            (1.2, 0.9, 0.5),
        ];
        let [mut sx, mut sy, _] = tpl.render(&truth, &x, &y);
        let mut seed = 7u64;
        for v in sx.iter_mut().chain(sy.iter_mut()) {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            *v += 1e-3 * ((seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5);
        }
        sx[[5, 7]] = f64::NAN;
        sy[[20, 30]] = f64::NAN;
        sx[[30, 10]] = f64::NAN;
        sy[[30, 10]] = f64::NAN;
        let guess = truth
            .iter()
            .enumerate()
            .map(|(k, &(bx, by, w))| BeadInit {
                x: bx + 0.013 * (k as f64 - 3.0),
                y: by - 0.009 * (k as f64 - 2.5),
                weight: w * 1.1,
            })
            .collect();
        (
            Image::new(sx, x.clone(), y.clone()),
            Image::new(sy, x, y),
            guess,
        )
    }

    /// |a − b| ≤ tol·scale elementwise.
    fn close(a: &[f64], b: &[f64], tol: f64, scale: f64) -> bool {
        a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x - y).abs() <= tol * scale)
    }

    #[test]
    fn block_sparse_accumulation_matches_the_pixel_major_reference() {
        let cubic = Template::analytic_standin(0.4, 0.02, 1.0).unwrap();
        let mut linear = cubic.clone();
        linear.grid.interp = crate::optics::grid::Interp::Linear;
        for tpl in [&cubic, &linear] {
            let (sx, sy, guess) = scene(tpl);
            let p: Vec<f64> = guess.iter().flat_map(|b| [b.weight, b.x, b.y]).collect();
            for channels in [Channels::Both, Channels::Sx, Channels::Sy] {
                let opts = FitOptions {
                    channels,
                    ..Default::default()
                };
                let d = FitData::new(&sx, &sy, tpl, &opts).unwrap();
                let (rss, jtj, jtr) = d.accumulate(&p);
                let (rss0, jtj0, jtr0) = d.accumulate_reference(&p, true);
                assert!(rss > 0.0 && jtj.amax() > 0.0);
                // The same sums in another order (separable stencil, blocked dot products):
                // equal to rounding.
                assert!(
                    (rss - rss0).abs() <= 1e-13 * rss0,
                    "{channels:?}: {rss} vs {rss0}"
                );
                assert!(
                    close(jtj.as_slice(), jtj0.as_slice(), 1e-13, jtj0.amax()),
                    "{channels:?}: JᵀJ differs by {}",
                    (&jtj - &jtj0).amax()
                );
                assert!(
                    close(jtr.as_slice(), jtr0.as_slice(), 1e-12, jtr0.amax()),
                    "{channels:?}: Jᵀr differs by {}",
                    (&jtr - &jtr0).amax()
                );
                // JᵀJ is symmetric exactly, as the reference's.
                assert_eq!(jtj, jtj.transpose());
                // Far-apart beads do not couple: beads 4 and 5 (2.35 µm apart in x, windows ±1 µm).
                assert_eq!(jtj[(12, 15)], 0.0);
            }
        }
    }

    #[test]
    fn tiled_model_images_match_the_template_render() {
        // 150 × 70 pixels: tiles of 128 × 32 leave partial tiles on both axes; beads straddling
        // tile borders, one half outside the image, one with zero weight.
        let tpl = Template::analytic_standin(0.4, 0.02, 1.0).unwrap();
        let x: Vec<f64> = (0..150).map(|i| 0.1 + i as f64 * 0.05).collect();
        let y: Vec<f64> = (0..70).map(|i| -0.2 + i as f64 * 0.05).collect();
        let beads = [
            (6.5, 1.4, 1.0),
            (6.47, 1.46, -0.3),
            (0.2, 0.0, 0.8),
            (3.3, 3.2, 1.2),
            (7.6, -0.1, 0.6),
            (2.0, 2.0, 0.0),
        ];
        let [sx, sy, _] = tpl.render(&beads, &x, &y);
        let (sx, sy) = (
            Image::new(sx, x.clone(), y.clone()),
            Image::new(sy, x.clone(), y.clone()),
        );
        let d = FitData::new(&sx, &sy, &tpl, &FitOptions::default()).unwrap();
        let p: Vec<f64> = beads
            .iter()
            .flat_map(|&(bx, by, w)| [w * tpl.norm_factor, bx, by])
            .collect();
        let [mx, my] = d.model(&p);
        for (m, r) in [(&mx, &sx.data), (&my, &sy.data)] {
            let peak = r.iter().fold(0.0f64, |a, v| a.max(v.abs()));
            assert!(peak > 0.1);
            let worst = m
                .iter()
                .zip(r)
                .fold(0.0f64, |a, (m, r)| a.max((m - r).abs()));
            assert!(
                worst <= 1e-12 * peak,
                "model vs render: {worst:e} of {peak}"
            );
        }
    }

    #[test]
    fn block_sparse_fit_reaches_the_reference_minimum() {
        let tpl = Template::analytic_standin(0.4, 0.02, 1.0).unwrap();
        let (sx, sy, guess) = scene(&tpl);
        let opts = FitOptions::default();
        let mut d = FitData::new(&sx, &sy, &tpl, &opts).unwrap();
        let new = d.fit_with_degeneracy(guess.clone(), &opts).unwrap();
        d.reference = true;
        let old = d.fit_with_degeneracy(guess, &opts).unwrap();
        assert_eq!(new.beads.len(), 7);
        assert!(new.total_evaluations > 3);
        // The same minimum: weights within 1e-9 relative, positions within 1e-6 nm, RSS within
        // 1e-12 relative, the same uncertainties to 1e-9 and the same degeneracy report.
        for (a, b) in new.beads.iter().zip(&old.beads) {
            assert!(
                (a.weight - b.weight).abs() <= 1e-9 * b.weight.abs(),
                "{a:?} vs {b:?}"
            );
            assert!(
                (a.x - b.x).abs() <= 1e-9 && (a.y - b.y).abs() <= 1e-9,
                "{a:?} vs {b:?}"
            );
            for (e, f) in [
                (a.weight_err, b.weight_err),
                (a.x_err, b.x_err),
                (a.y_err, b.y_err),
            ] {
                let (e, f) = (e.unwrap(), f.unwrap());
                assert!((e - f).abs() <= 1e-9 * f, "{a:?} vs {b:?}");
            }
        }
        assert!((new.rss - old.rss).abs() <= 1e-12 * old.rss);
        assert!((new.condition - old.condition).abs() <= 1e-6 * old.condition);
        let dm = (&new.model_sx.data - &old.model_sx.data)
            .iter()
            .chain((&new.model_sy.data - &old.model_sy.data).iter())
            .fold(0.0f64, |m, v| m.max(v.abs()));
        assert!(dm <= 1e-9 * old.model_sx.data.iter().fold(0.0f64, |m, v| m.max(v.abs())));
        assert_eq!(new.degeneracies.len(), old.degeneracies.len());
        assert_eq!(new.status, old.status);
    }
}
