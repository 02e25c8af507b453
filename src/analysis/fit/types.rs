//! The fit's vocabulary: its options (channels, initial guesses, how beads are added) and its
//! result (beads, degeneracies, the model and residual images), shared by the parts of the fit.

use super::super::sensitivity::Stencil;
use super::super::{check_above, check_range, AnalysisError, Result};
use super::lm::FitStatus;
use crate::data::Image;
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
    pub(super) fn list(&self) -> &'static [usize] {
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

/// An initial guess: position (µm) and weight (reference-bead units). Declared beside the
/// template (which renders such beads) so that the Cramér–Rao bounds, which the fit reports,
/// need not import the fit.
pub use crate::analysis::template::BeadInit;

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
    /// σ (µm) of the Gaussian the detection map is smoothed with before its maxima are taken
    /// ([`DETECT_SMOOTH_UM`]); 0: not smoothed (background removal, whose
    /// objects sit on a filament that smoothing along its line would favour).
    pub detect_smooth_um: f64,
    /// Vacuum wavelength, nm, for the template's size domain (`analysis::domain`); the
    /// `fit_beads` binding takes it from the session's optics.
    pub wavelength_nm: f64,
    /// Refractive index of the beads, for the diameter their weight implies (default: the
    /// template reference's).
    pub bead_n: Option<f64>,
    /// Where the grow step looks for the next bead.
    pub grow_candidates: GrowCandidates,
}

/// Where the grow step takes its candidates for one more bead.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum GrowCandidates {
    /// The strongest maxima of the residual's matched filter: the χ² gain of one added bead of
    /// the template's shape (the default; the detector a bead in white noise calls for).
    #[default]
    MatchedFilter,
    /// The strongest maxima of the residual's detection map ∂Sx/∂x + ∂Sy/∂y (smoothed by
    /// `detect_smooth_um`): point-like features only. The background removal of a filament scan
    /// (Sec. 6) grows this way: in the one fitted channel the filament's own faint response is
    /// a line, which the matched filter takes for a row of beads (their subtraction erased the
    /// filament from Sx).
    DetectionMap,
}

/// The σ of the Gaussian the detection map is smoothed with before its maximum is taken, µm:
/// small beside the map's peak (≈ 0.15 µm wide in the paper's beam: the peak drops by ≈ 4 %),
/// large beside the smallest pixels (10 nm), so the maximum's noise no longer grows as 1/pixel.
pub(crate) const DETECT_SMOOTH_UM: f64 = 0.04;

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
            detect_smooth_um: DETECT_SMOOTH_UM,
            wavelength_nm: crate::optics::params::Optics::default().wavelength_nm,
            bead_n: None,
            grow_candidates: GrowCandidates::MatchedFilter,
        }
    }
}

impl FitOptions {
    pub(super) fn validate(&self) -> Result<()> {
        check_range("ftol", self.ftol, 0.0, 1.0)?;
        check_range("detect_smooth_um", self.detect_smooth_um, 0.0, 1.0)?;
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
        check_range("wavelength_nm", self.wavelength_nm, 100.0, 10_000.0)?;
        if let Some(n) = self.bead_n {
            check_range("bead_n", n, 1.0, 4.0)?;
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
    /// Cramér–Rao bounds (1σ floors) of x, y (µm) and weight from the scan's Sx and Sy pixels
    /// at the fitted parameters with the fit's σ (`analysis::crlb::beads_crlb`): with σ given
    /// and both channels fitted they equal the fit's own 1σ (least squares is efficient here);
    /// a one-channel fit's 1σ is larger, by how much the other channel would have told. None
    /// when the bound does not exist (a weight of 0, a singular information matrix) or was not
    /// computed.
    #[serde(default)]
    pub x_crlb: Option<f64>,
    #[serde(default)]
    pub y_crlb: Option<f64>,
    #[serde(default)]
    pub weight_crlb: Option<f64>,
}

/// A bead is found when its weight is significantly positive: C − `FOUND_SIGMA`·σ_C > 0. Three
/// standard deviations, one-sided: on pure noise a fitted bead passes with probability 0.13 %
/// (Gaussian), where 2σ would "find" one bead in 44; a real bead at the paper's noise (weights
/// known to a few %) passes by a wide margin.
pub const FOUND_SIGMA: f64 = 3.0;

impl Bead {
    /// The bead as a start or a model bead: position and weight.
    pub fn init(&self) -> BeadInit {
        BeadInit {
            x: self.x,
            y: self.y,
            weight: self.weight,
        }
    }
    /// Whether the weight is significantly positive (see [`FOUND_SIGMA`]). Without an
    /// uncertainty (an ill-conditioned fit, reported in `degeneracies`) a positive weight counts.
    pub fn found(&self) -> bool {
        match self.weight_err {
            Some(e) if e.is_finite() => self.weight - FOUND_SIGMA * e > 0.0,
            _ => self.weight.is_finite() && self.weight > 0.0,
        }
    }
    /// Whether the weight is within 2σ of zero (reported as [`Degeneracy::Insignificant`]).
    pub fn insignificant(&self) -> bool {
        self.weight.abs() < 1e-9 || self.weight_err.is_some_and(|e| self.weight.abs() < 2.0 * e)
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
    /// Where the answer leaves its domain, in words (`analysis::domain`); empty when the beads'
    /// positions, weights and σ hold.
    #[serde(default)]
    pub warnings: Vec<String>,
    /// Each bead's own warnings (not found, outside the template's size domain, not whole inside
    /// the scan), by bead index; `warnings` holds these and those about the whole fit. A bead's
    /// values hold when its own list and the whole fit's warnings are empty.
    #[serde(default)]
    pub bead_warnings: Vec<Vec<String>>,
}

impl FitResult {
    /// The warnings about the whole fit (not converged, no bead found, degeneracies, misfit):
    /// `warnings` without the beads' own.
    pub fn whole_fit_warnings(&self) -> &[String] {
        let own: usize = self.bead_warnings.iter().map(Vec::len).sum();
        &self.warnings[..self.warnings.len().saturating_sub(own)]
    }
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

/// One bead replacing two: weights summed, position |C|-weighted.
pub(crate) fn merge_pair(a: BeadInit, b: BeadInit) -> BeadInit {
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
