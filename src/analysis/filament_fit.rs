//! A straight bead-model filament (Sec. 4.2) as a parametric model of the whole Sx/Sy image,
//! its Cramér–Rao bounds, and its least-squares fit to a scan.
//!
//! **Model.** A straight filament crossing the scan, cut into sections every `spacing_um` along
//! its axis; each section responds like the template's reference bead times its weight
//! λ·h (λ = weight per µm in reference-bead units, Sec. 4.2: 3d²·n_corr/(2d_ref³) per unit
//! length, i.e. the cylinder's volume per length over the reference bead's volume, times
//! n_corr). Parameters θ = (offset c µm, angle θ, λ, b_x, b_y):
//! - the axis passes through F = P + c·n̂ with P the fixed reference point `centre` and
//!   n̂ = (cos θ, −sin θ) its normal; it runs along ê = (sin θ, cos θ) (angle from the QPD +y axis
//!   towards +x, as every filament angle in the crate);
//! - sections sit at F + t_k·ê with t_k on a fixed lattice k·h, over every t whose section the
//!   template can carry onto a pixel (so the model is smooth in θ: the lattice does not move
//!   with the parameters; the filament's ends lie outside the reach of the scan — the domain of
//!   this model);
//! - μ_ch(s) = (λh/f)·Σ_k T_ch(s − p_k) + b_ch, in the scan's (instrument) units (f the
//!   template's `norm_factor`), with the analytic gradient ∂μ/∂c = −(λh/f)Σ∇T·n̂,
//!   ∂μ/∂θ = −(λh/f)Σ∇T·(c·∂n̂/∂θ + t_k·∂ê/∂θ), ∂μ/∂λ = (h/f)ΣT, ∂μ/∂b_ch = 1.
//!
//! Quantities from λ: volume per µm V = λ·V_ref/n_corr(n_obj) (nm³/µm), linear density
//! μ = ρ·V (eq. mtLinDens), diameter d = √(4V/(π·1000 nm)) (eq. colDiam's cylinder). Their
//! relative bounds follow: σ_μ/μ = σ_λ/λ, σ_d/d = σ_λ/(2λ). The maximum sensitivity the per-row
//! method reads is proportional to λ, so its bound is σ_λ times the sensitivity per unit λ.

use super::crlb::Fisher;
use super::template::Template;
use super::{check_above, check_range, AnalysisError, AxisMap, Result};
use serde::{Deserialize, Serialize};

/// Parameters of the model, in order: offset (µm), angle (rad), λ (reference-bead units/µm),
/// background Sx, background Sy (instrument units).
pub const LINE_PARAMS: [&str; 5] = [
    "offset",
    "angle",
    "weight per length",
    "Sx background",
    "Sy background",
];

/// A straight filament through the scan (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LineFilament {
    /// Reference point P, µm (e.g. the scan's centre).
    pub centre: [f64; 2],
    /// Signed distance of the axis from P along n̂ = (cos θ, −sin θ), µm.
    pub offset_um: f64,
    /// Angle from the QPD +y axis towards +x, degrees.
    pub angle_deg: f64,
    /// Weight per length, reference-bead units per µm.
    pub lambda: f64,
    /// Constant background of Sx and Sy, instrument units.
    pub background: [f64; 2],
    /// Section spacing along the axis, µm (paper: 0.05).
    pub spacing_um: f64,
}

impl LineFilament {
    pub fn validate(&self) -> Result<()> {
        for (name, v) in [
            ("centre.x", self.centre[0]),
            ("centre.y", self.centre[1]),
            ("offset_um", self.offset_um),
            ("angle_deg", self.angle_deg),
            ("lambda", self.lambda),
            ("background.sx", self.background[0]),
            ("background.sy", self.background[1]),
        ] {
            if !v.is_finite() {
                return Err(AnalysisError::OutOfRange {
                    name,
                    value: v,
                    allowed: "finite".into(),
                });
            }
        }
        check_range("spacing_um", self.spacing_um, 1e-3, 0.5)?;
        Ok(())
    }

    /// The parameter vector θ (angle in radians).
    pub fn params(&self) -> [f64; 5] {
        [
            self.offset_um,
            self.angle_deg.to_radians(),
            self.lambda,
            self.background[0],
            self.background[1],
        ]
    }

    /// The filament with parameters θ (angle in radians), other fields kept.
    pub fn with_params(&self, p: &[f64]) -> Self {
        Self {
            offset_um: p[0],
            angle_deg: p[1].to_degrees(),
            lambda: p[2],
            background: [p[3], p[4]],
            ..*self
        }
    }

    /// A point of the axis (the foot of the normal from P), µm.
    pub fn foot(&self) -> [f64; 2] {
        let t = self.angle_deg.to_radians();
        [
            self.centre[0] + self.offset_um * t.cos(),
            self.centre[1] - self.offset_um * t.sin(),
        ]
    }
}

/// Model and gradient of one channel at every pixel (row-major): (μ, ∂μ/∂c, ∂μ/∂θ, ∂μ/∂λ);
/// ∂μ/∂b is 1 for the pixel's own channel.
pub type LineEval = [Vec<[f64; 4]>; 2];

/// Evaluate the model (Sx and Sy) and its gradient on the pixel grid `x` (columns) × `y` (rows),
/// µm. See the module docs.
pub fn line_eval(tpl: &Template, fil: &LineFilament, x: &[f64], y: &[f64]) -> Result<LineEval> {
    fil.validate()?;
    super::check_axis("x", x, 1)?;
    super::check_axis("y", y, 1)?;
    let (nx, ny) = (x.len(), y.len());
    let mut out: LineEval = [vec![[0.0; 4]; nx * ny], vec![[0.0; 4]; nx * ny]];
    let th = fil.angle_deg.to_radians();
    let (s, c) = th.sin_cos();
    let e = [s, c];
    let n = [c, -s];
    let de = [c, -s]; // ∂ê/∂θ
    let dn = [-s, -c]; // ∂n̂/∂θ
    let foot = fil.foot();
    let h = fil.spacing_um;
    let inv_f = 1.0 / tpl.norm_factor;
    let ((u0, u1), (v0, v1)) = tpl.extent();
    // the arc range whose sections reach a pixel: corners of the scan grown by the template
    let (xa, xb) = (x[0].min(x[nx - 1]) - u1, x[0].max(x[nx - 1]) - u0);
    let (ya, yb) = (y[0].min(y[ny - 1]) - v1, y[0].max(y[ny - 1]) - v0);
    let proj = |px: f64, py: f64| (px - foot[0]) * e[0] + (py - foot[1]) * e[1];
    let ts = [proj(xa, ya), proj(xa, yb), proj(xb, ya), proj(xb, yb)];
    let t0 = ts.iter().cloned().fold(f64::INFINITY, f64::min);
    let t1 = ts.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
    let (k0, k1) = ((t0 / h).floor() as i64, (t1 / h).ceil() as i64);
    if k1 - k0 > 2_000_000 {
        return Err(AnalysisError::OutOfRange {
            name: "spacing_um",
            value: h,
            allowed: format!("at most 2·10⁶ sections over {} µm", t1 - t0),
        });
    }
    let (ax, ay) = (AxisMap::new(x), AxisMap::new(y));
    let w = fil.lambda * h * inv_f;
    for k in k0..=k1 {
        let t = k as f64 * h;
        let p = [foot[0] + t * e[0], foot[1] + t * e[1]];
        let dpt = [
            fil.offset_um * dn[0] + t * de[0],
            fil.offset_um * dn[1] + t * de[1],
        ];
        let cols = ax.range(p[0] + u0, p[0] + u1);
        if cols.is_empty() {
            continue;
        }
        for r in ay.range(p[1] + v0, p[1] + v1) {
            let v = y[r] - p[1];
            for cidx in cols.clone() {
                let g = tpl.eval_grad(x[cidx] - p[0], v);
                let i = r * nx + cidx;
                for ch in 0..2 {
                    let o = &mut out[ch][i];
                    o[0] += w * g.v[ch];
                    o[1] -= w * (g.du[ch] * n[0] + g.dv[ch] * n[1]);
                    o[2] -= w * (g.du[ch] * dpt[0] + g.dv[ch] * dpt[1]);
                    o[3] += h * inv_f * g.v[ch];
                }
            }
        }
    }
    for ch in 0..2 {
        for o in out[ch].iter_mut() {
            o[0] += fil.background[ch];
        }
    }
    Ok(out)
}

/// Cramér–Rao bounds of the line filament's parameters (1σ floors).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LineBound {
    pub offset_um: f64,
    pub angle_deg: f64,
    /// Weight per length, reference-bead units/µm.
    pub lambda: f64,
    /// Relative bound of λ, and so of the linear density and the corrected maximum
    /// sensitivity (σ_λ/λ; infinite when λ = 0).
    pub lambda_rel: f64,
    /// Relative bound of the diameter, σ_λ/(2λ).
    pub diameter_rel: f64,
    /// Backgrounds (Sx, Sy), instrument units.
    pub background: [f64; 2],
}

/// Fisher information of the line filament evaluated on a grid `nx` columns wide (`ev`, see
/// [`line_eval`]), channels `channels` (0 = Sx, 1 = Sy), per-pixel noise `sigma(ch, row, col)`
/// (None: pixel not taken). Parameter order [`LINE_PARAMS`]; a background of a channel not
/// used is fixed (its row is the identity so that the matrix stays invertible, and its bound is
/// reported as 0).
pub(crate) fn fisher_of_eval(
    ev: &LineEval,
    nx: usize,
    channels: &[usize],
    sigma: &dyn Fn(usize, usize, usize) -> Option<f64>,
) -> Fisher {
    let mut f = Fisher::new(5);
    for &ch in channels {
        for (i, o) in ev[ch].iter().enumerate() {
            let Some(s) = sigma(ch, i / nx, i % nx) else {
                continue;
            };
            let mut g = [o[1], o[2], o[3], 0.0, 0.0];
            g[3 + ch] = 1.0;
            f.add(&g, s);
        }
    }
    for ch in 0..2 {
        if !channels.contains(&ch) {
            f.info[(3 + ch, 3 + ch)] = 1.0;
        }
    }
    f
}

/// Bounds from a Fisher matrix of the line model (see [`fisher_of_eval`]).
pub fn line_bound(f: &Fisher, fil: &LineFilament, channels: &[usize]) -> Result<LineBound> {
    let b = f.bounds(&LINE_PARAMS)?;
    let rel = if fil.lambda != 0.0 {
        b[2] / fil.lambda.abs()
    } else {
        f64::INFINITY
    };
    let bg = |ch: usize| {
        if channels.contains(&ch) {
            b[3 + ch]
        } else {
            0.0
        }
    };
    Ok(LineBound {
        offset_um: b[0],
        angle_deg: b[1].to_degrees(),
        lambda: b[2],
        lambda_rel: rel,
        diameter_rel: 0.5 * rel,
        background: [bg(0), bg(1)],
    })
}

/// The Cramér–Rao bounds of a straight filament's offset, angle, weight per length and
/// backgrounds from the pixels of the grid `x` × `y` (µm) in `channels`, each with noise
/// `sigma(ch, row, col)` (instrument units; None: not taken). Errors: bad model parameters, a
/// filament the data carry no information about (λ = 0 gives no information about its angle or
/// offset), a singular information matrix.
pub fn line_crlb(
    tpl: &Template,
    fil: &LineFilament,
    x: &[f64],
    y: &[f64],
    channels: &[usize],
    sigma: &dyn Fn(usize, usize, usize) -> Option<f64>,
) -> Result<LineBound> {
    let ev = line_eval(tpl, fil, x, y)?;
    line_bound(
        &fisher_of_eval(&ev, x.len(), channels, sigma),
        fil,
        channels,
    )
}

/// Volume per µm of a filament (nm³/µm) from its weight per length λ (reference-bead units/µm)
/// and index `n_obj`: V = λ·V_ref/n_corr (Sec. 4.2; n_corr eq. nCor). Errors: an index at or
/// below the medium's (no contrast).
pub fn volume_per_um(tpl: &Template, lambda: f64, n_obj: f64) -> Result<f64> {
    let r = tpl.reference;
    let nc = super::scaling::n_corr(n_obj, r.n, r.n_medium)?;
    check_above("n_corr", nc, 0.0)?;
    Ok(lambda * r.volume_nm3() / nc)
}

/// Weight per length (reference-bead units/µm) of a uniform cylinder of diameter `d_nm` and
/// index `n_obj`: 3d²·n_corr/(2d_ref³) per nm (Sec. 4.2), × 1000 nm/µm.
pub fn lambda_of_diameter(tpl: &Template, d_nm: f64, n_obj: f64) -> Result<f64> {
    check_range("d_nm", d_nm, 0.0, 5000.0)?;
    super::bead_model::section_weight(tpl, d_nm, 1000.0, n_obj)
}

/// Options of [`fit_line_filament`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct LineFitOptions {
    /// Pixel noise σ (instrument units); None: estimated from the residuals.
    pub sigma: Option<f64>,
    /// Section spacing of the model, µm (paper: 0.05).
    pub spacing_um: f64,
    /// Angle step of the initial search, degrees.
    pub search_step_deg: f64,
    /// MINPACK tolerances and evaluation budget of the solver (`fit::lm`).
    pub tol: f64,
    pub patience: usize,
}

impl Default for LineFitOptions {
    fn default() -> Self {
        Self {
            sigma: None,
            spacing_um: 0.05,
            search_step_deg: 2.5,
            tol: 1e-10,
            patience: 100,
        }
    }
}

/// Result of [`fit_line_filament`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LineFitResult {
    /// The fitted filament (reference point: the scan's centre).
    pub filament: LineFilament,
    /// 1σ from the covariance σ²(JᵀJ)⁻¹ at the solution (offset µm, angle °, λ, backgrounds).
    pub err: LineBound,
    /// The Cramér–Rao bounds of the scan's pixels at the fitted parameters with the fit's σ.
    pub crlb: LineBound,
    pub sigma: f64,
    pub sigma_estimated: bool,
    pub rss: f64,
    pub n_residuals: usize,
    /// The initial guess of the search (angle °, offset µm, λ).
    pub start: [f64; 3],
    pub status: crate::analysis::fit::FitStatus,
    pub reason: String,
    pub iterations: usize,
    /// The pixel noise of the residuals measured without the residuals' spread: 1.4826·MAD of
    /// their first differences along rows, / √2 (Sx and Sy together): what the residual RMS is
    /// compared with.
    #[serde(default)]
    pub pixel_noise: f64,
    /// RMS of the fitted line's signal (model minus backgrounds) over the pixels.
    #[serde(default)]
    pub signal_rms: f64,
    /// Where the answer leaves its domain, in words; empty when the numbers and their σ hold
    /// (see [`line_fit_warnings`]).
    #[serde(default)]
    pub warnings: Vec<String>,
}

/// Residual RMS above this multiple of the data's own pixel noise flags a model that does not
/// describe the image.
pub const MISFIT_RATIO: f64 = 1.2;
/// The misfit ratio's limit for `n` residuals: [`MISFIT_RATIO`], or 5 standard errors of the
/// ratio of white noise when that is larger (small images: the RMS of n residuals has a relative
/// error of 1/√(2n), the MAD of their ~n first differences √(1.36/n) — the MAD's efficiency of
/// 37 % — so a 25×10 strip's ratio scatters by 6 %).
pub fn misfit_limit(n: usize) -> f64 {
    let n = n.max(1) as f64;
    MISFIT_RATIO.max(1.0 + 5.0 * (1.0 / (2.0 * n) + 1.36 / n).sqrt())
}
/// ... and above this fraction of the line's signal RMS (noise-free data: the template's
/// interpolation leaves residuals of ~0.5 % of the signal).
pub const MISFIT_SIGNAL_FRACTION: f64 = 0.02;
/// λ below this multiple of its 1σ: no filament distinguishable from noise.
pub const DETECT_SIGMAS: f64 = 5.0;

/// The domain checks of the whole-image fit, in words (empty: inside the domain):
/// - the optimiser converged;
/// - λ is at least [`DETECT_SIGMAS`] of its 1σ above zero (else the line may be noise);
/// - the residual RMS is within [`misfit_limit`] of the residuals' pixel noise from their
///   first differences (else the image holds more than one straight uniform filament: other objects, a
///   bend, an end inside the scan, a diameter that changes — and λ's σ does not hold), unless
///   they are under [`MISFIT_SIGNAL_FRACTION`] of the signal's RMS (noise-free data).
pub fn line_fit_warnings(r: &LineFitResult) -> Vec<String> {
    use crate::analysis::fit::FitStatus;
    let mut w = Vec::new();
    if r.status != FitStatus::Converged {
        w.push(format!(
            "the fit stopped before converging ({:?}: {})",
            r.status, r.reason
        ));
    }
    let l = r.filament.lambda;
    if !(l > DETECT_SIGMAS * r.err.lambda) {
        w.push(format!(
            "weak line: λ = {l:.4} is {:.1}σ above zero (under {DETECT_SIGMAS}σ): it may be noise",
            l / r.err.lambda
        ));
    }
    let rms = (r.rss / r.n_residuals.max(1) as f64).sqrt();
    let k = if r.pixel_noise > 0.0 {
        rms / r.pixel_noise
    } else {
        f64::INFINITY
    };
    let limit = misfit_limit(r.n_residuals);
    if k > limit && rms > MISFIT_SIGNAL_FRACTION * r.signal_rms {
        w.push(format!(
            "misfit: the residuals are {k:.2}× the pixel noise (over {limit:.2}×) and {:.1} % of the signal: the image holds more than one straight uniform filament (other objects, a bend, an end inside the scan); λ's σ does not hold",
            100.0 * rms / r.signal_rms
        ));
    }
    w
}

/// The line spread of a unit-λ filament at `angle_deg`: P(d) = h·Σ_k T(d·n̂ + k·h·ê)/f for the
/// perpendicular distances d = d0 + i·step (Sx, Sy).
fn line_profile(
    tpl: &Template,
    angle_deg: f64,
    h: f64,
    d0: f64,
    step: f64,
    n: usize,
) -> [Vec<f64>; 2] {
    let (s, c) = angle_deg.to_radians().sin_cos();
    let (e, nn) = ([s, c], [c, -s]);
    let ((u0, u1), (v0, v1)) = tpl.extent();
    let reach = u1.max(-u0).max(v1).max(-v0) * std::f64::consts::SQRT_2;
    let kmax = (reach / h).ceil() as i64;
    let mut out = [vec![0.0; n], vec![0.0; n]];
    for i in 0..n {
        let d = d0 + i as f64 * step;
        for k in -kmax..=kmax {
            let t = k as f64 * h;
            let v = tpl.eval(d * nn[0] + t * e[0], d * nn[1] + t * e[1]);
            out[0][i] += v[0];
            out[1][i] += v[1];
        }
        out[0][i] *= h / tpl.norm_factor;
        out[1][i] *= h / tpl.norm_factor;
    }
    out
}

/// Initial guess (angle °, offset µm, λ) for a filament crossing the scan: for every angle on a
/// grid over 180° and every offset on a grid of about half a pixel, the least-squares λ and
/// constant backgrounds of the unit-λ line model (its line spread shifted to the offset) and the
/// RSS they remove, (Σ⟨m̃, d̃⟩)²/Σ⟨m̃, m̃⟩ (m̃, d̃ mean-subtracted per channel); the largest with
/// λ > 0 wins (a matched filter of the whole image). Per angle the pixels are binned once by
/// their distance from the line through the centre on the line spread's own 10 nm grid, and
/// offsets are whole multiples of that grid, so each offset costs one pass over the occupied
/// bins, not over the pixels (a start value: 10 nm of quantisation is far below the beam).
fn search(
    tpl: &Template,
    sx: &crate::data::Image,
    sy: &crate::data::Image,
    centre: [f64; 2],
    opts: &LineFitOptions,
) -> Option<[f64; 3]> {
    let (x, y) = (&sx.x, &sx.y);
    let px = (x[1] - x[0]).abs().min((y[1] - y[0]).abs());
    let half = 0.5 * ((x[x.len() - 1] - x[0]).powi(2) + (y[y.len() - 1] - y[0]).powi(2)).sqrt();
    let ((u0, u1), _) = tpl.extent();
    let step = 0.01;
    let dmax = half + u1.max(-u0);
    let nd = (2.0 * dmax / step).ceil() as usize + 1;
    let j_step = ((0.5 * px / step).round() as i64).max(1);
    let j_max = (half / step).floor() as i64;
    let data = [&sx.data, &sy.data];
    let means: Vec<f64> = data
        .iter()
        .map(|d| {
            let v: Vec<f64> = d.iter().copied().filter(|v| v.is_finite()).collect();
            v.iter().sum::<f64>() / v.len().max(1) as f64
        })
        .collect();
    let n_ang = (180.0 / opts.search_step_deg).round().max(4.0) as usize;
    let mut best: Option<(f64, [f64; 3])> = None;
    // per channel: pixel count and Σ(data − mean) per distance bin, occupied bins
    let mut cnt = [vec![0.0; nd], vec![0.0; nd]];
    let mut sdd = [vec![0.0; nd], vec![0.0; nd]];
    let mut occupied: [Vec<usize>; 2] = [Vec::new(), Vec::new()];
    for ia in 0..n_ang {
        let ang = -90.0 + (ia as f64 + 0.5) * 180.0 / n_ang as f64;
        let prof = line_profile(tpl, ang, opts.spacing_um, -dmax, step, nd);
        let (s, c) = ang.to_radians().sin_cos();
        let mut tot = [(0.0, 0.0); 2]; // (n, Σ d̃) per channel
        for ch in 0..2 {
            for &b in &occupied[ch] {
                cnt[ch][b] = 0.0;
                sdd[ch][b] = 0.0;
            }
            occupied[ch].clear();
            for (r, &yr) in y.iter().enumerate() {
                for (ci, &xc) in x.iter().enumerate() {
                    let dv = data[ch][[r, ci]];
                    if !dv.is_finite() {
                        continue;
                    }
                    let d = (xc - centre[0]) * c - (yr - centre[1]) * s;
                    let b = ((d + dmax) / step).round();
                    if b < 0.0 || b as usize >= nd {
                        continue;
                    }
                    let b = b as usize;
                    if cnt[ch][b] == 0.0 {
                        occupied[ch].push(b);
                    }
                    let dd = dv - means[ch];
                    cnt[ch][b] += 1.0;
                    sdd[ch][b] += dd;
                    tot[ch].0 += 1.0;
                    tot[ch].1 += dd;
                }
            }
        }
        for j in (-j_max / j_step)..=(j_max / j_step) {
            let j = j * j_step;
            let (mut md, mut mm) = (0.0, 0.0);
            for ch in 0..2 {
                let (n, sd) = tot[ch];
                if n == 0.0 {
                    continue;
                }
                let (mut sm, mut smm, mut smd) = (0.0, 0.0, 0.0);
                for &b in &occupied[ch] {
                    let i = b as i64 - j;
                    if i < 0 || i as usize >= nd {
                        continue;
                    }
                    let m = prof[ch][i as usize];
                    sm += cnt[ch][b] * m;
                    smm += cnt[ch][b] * m * m;
                    smd += sdd[ch][b] * m;
                }
                mm += smm - sm * sm / n;
                md += smd - sm * sd / n;
            }
            if mm > 0.0 && md > 0.0 {
                let score = md * md / mm;
                if best.is_none_or(|(b, _)| score > b) {
                    best = Some((score, [ang, j as f64 * step, md / mm]));
                }
            }
        }
    }
    best.map(|(_, p)| p)
}

/// Fit the straight bead-model filament (offset, angle, weight per length λ, a background per
/// channel) to the whole Sx and Sy images of an XY scan by least squares with the project's
/// Levenberg–Marquardt (`fit::lm`), from a matched-filter search over angle and offset (or
/// from `init`). Beside the paper's per-row maxima (`orientation::measure_filament`), not
/// instead of them. Domain: one straight filament of uniform λ whose ends lie outside the
/// template's reach of the scan; white pixel noise. Errors: images of different shapes or
/// irregular axes, a scan smaller than 4×4, no finite pixel, no filament-like signal (the search
/// finds no positive λ), a fit that ends without a finite covariance.
pub fn fit_line_filament(
    sx: &crate::data::Image,
    sy: &crate::data::Image,
    tpl: &Template,
    init: Option<&LineFilament>,
    opts: &LineFitOptions,
) -> Result<LineFitResult> {
    use crate::analysis::fit::{levenberg_marquardt, Tolerances};
    check_range("spacing_um", opts.spacing_um, 1e-3, 0.5)?;
    check_range("search_step_deg", opts.search_step_deg, 0.1, 45.0)?;
    check_range("tol", opts.tol, 0.0, 1.0)?;
    if let Some(s) = opts.sigma {
        check_above("sigma", s, 0.0)?;
    }
    if sx.data.dim() != sy.data.dim() || sx.x != sy.x || sx.y != sy.y {
        return Err(AnalysisError::BadInput {
            name: "scan",
            reason: "Sx and Sy images differ in shape or axes".into(),
        });
    }
    super::kind::require_plane("the whole-image filament fit", sx, &["XY"])?;
    super::check_axis("x", &sx.x, 4)?;
    super::check_axis("y", &sx.y, 4)?;
    let (x, y) = (&sx.x, &sx.y);
    let nx = x.len();
    let centre = [0.5 * (x[0] + x[nx - 1]), 0.5 * (y[0] + y[y.len() - 1])];
    let data = [&sx.data, &sy.data];
    let m = data
        .iter()
        .map(|d| d.iter().filter(|v| v.is_finite()).count())
        .sum::<usize>();
    if m <= 5 {
        return Err(AnalysisError::BadInput {
            name: "scan",
            reason: format!("{m} finite pixels; the fit needs more than 5"),
        });
    }
    let (start, fil0) = match init {
        Some(f) => {
            f.validate()?;
            ([f.angle_deg, f.offset_um, f.lambda], *f)
        }
        None => {
            let s = search(tpl, sx, sy, centre, opts).ok_or_else(|| {
                AnalysisError::Failed(
                    "no filament found: no line through the scan correlates positively with the data"
                        .into(),
                )
            })?;
            let f = LineFilament {
                centre,
                offset_um: s[1],
                angle_deg: s[0],
                lambda: s[2],
                background: [0.0, 0.0],
                spacing_um: opts.spacing_um,
            };
            (s, f)
        }
    };
    let eval_err = std::cell::Cell::new(None);
    let eval = |p: &[f64]| {
        let f = fil0.with_params(p);
        let mut a = nalgebra::DMatrix::zeros(5, 5);
        let mut g = nalgebra::DVector::zeros(5);
        let mut rss = 0.0;
        match line_eval(tpl, &f, x, y) {
            Ok(ev) => {
                for ch in 0..2 {
                    for (i, o) in ev[ch].iter().enumerate() {
                        let d = data[ch][[i / nx, i % nx]];
                        if !d.is_finite() {
                            continue;
                        }
                        let r = o[0] - d;
                        let mut j = [o[1], o[2], o[3], 0.0, 0.0];
                        j[3 + ch] = 1.0;
                        rss += r * r;
                        for u in 0..5 {
                            g[u] += j[u] * r;
                            for v in 0..5 {
                                a[(u, v)] += j[u] * j[v];
                            }
                        }
                    }
                }
            }
            Err(e) => {
                eval_err.set(Some(e));
                rss = f64::NAN;
            }
        }
        (rss, a, g)
    };
    let raw = levenberg_marquardt(
        eval,
        fil0.params().to_vec(),
        &Tolerances {
            ftol: opts.tol,
            xtol: opts.tol,
            gtol: opts.tol,
            patience: opts.patience,
        },
    );
    if let Some(e) = eval_err.take() {
        return Err(e);
    }
    let mut fil = fil0.with_params(&raw.p);
    // one orientation: angle in (−90°, 90°]
    if fil.angle_deg > 90.0 || fil.angle_deg <= -90.0 {
        let a = (fil.angle_deg + 90.0).rem_euclid(180.0) - 90.0;
        let a = if a == -90.0 { 90.0 } else { a };
        let flips = ((fil.angle_deg - a) / 180.0).round() as i64;
        if flips % 2 != 0 {
            fil.offset_um = -fil.offset_um;
        }
        fil.angle_deg = a;
    }
    let dof = m.saturating_sub(5).max(1);
    let (sigma, est) = match opts.sigma {
        Some(s) => (s, false),
        None => ((raw.rss / dof as f64).sqrt(), true),
    };
    let info = Fisher {
        info: raw.jtj.clone() / (sigma * sigma),
        n_samples: m,
    };
    let err = line_bound(&info, &fil, &[0, 1])?;
    let valid = |ch: usize, r: usize, c: usize| data[ch][[r, c]].is_finite().then_some(sigma);
    let crlb = line_crlb(tpl, &fil, x, y, &[0, 1], &valid)?;
    let (noise, ss) = residual_noise_and_signal(tpl, &fil, x, y, &data)?;
    let mut out = LineFitResult {
        filament: fil,
        err,
        crlb,
        sigma,
        sigma_estimated: est,
        rss: raw.rss,
        n_residuals: m,
        start,
        status: raw.status,
        reason: raw.reason,
        iterations: raw.iterations,
        pixel_noise: noise,
        signal_rms: (ss / m as f64).sqrt(),
        warnings: vec![],
    };
    out.warnings = line_fit_warnings(&out);
    Ok(out)
}

/// The residuals' own pixel noise — 1.4826·MAD of their first differences along rows, / √2 (a
/// misfit's residual is smooth and localised: it raises the RMS, not the differences' MAD) —
/// and Σ(model − background)² over the finite pixels.
fn residual_noise_and_signal(
    tpl: &Template,
    fil: &LineFilament,
    x: &[f64],
    y: &[f64],
    data: &[&ndarray::Array2<f64>; 2],
) -> Result<(f64, f64)> {
    let nx = x.len();
    let ev = line_eval(tpl, fil, x, y)?;
    let mut ss = 0.0;
    let mut diffs = Vec::new();
    for ch in 0..2 {
        let mut prev: Option<(usize, f64)> = None;
        for (i, o) in ev[ch].iter().enumerate() {
            let d = data[ch][[i / nx, i % nx]];
            if !d.is_finite() {
                prev = None;
                continue;
            }
            ss += (o[0] - fil.background[ch]).powi(2);
            let res = d - o[0];
            if let Some((j, pr)) = prev {
                if j / nx == i / nx {
                    diffs.push(res - pr);
                }
            }
            prev = Some((i, res));
        }
    }
    let noise = super::stats::robust_std(&diffs).unwrap_or(0.0) / std::f64::consts::SQRT_2;
    Ok((noise, ss))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::analysis::bead_model::{render_scene, BeadModelOptions};

    fn axis(n: usize, h: f64) -> Vec<f64> {
        (0..n).map(|i| i as f64 * h).collect()
    }

    /// The stand-in template, a square grid of `n` pixels of `h` µm, and the line model of
    /// `f` evaluated on it.
    fn eval_on_grid(f: &LineFilament, n: usize, h: f64) -> (Template, Vec<f64>, LineEval) {
        let tpl = Template::analytic_standin(0.4, 0.02, 1.6).unwrap();
        let xs = axis(n, h);
        let ev = line_eval(&tpl, f, &xs, &xs).unwrap();
        (tpl, xs, ev)
    }

    fn fil(angle: f64, offset: f64, lambda: f64) -> LineFilament {
        LineFilament {
            centre: [1.0, 1.0],
            offset_um: offset,
            angle_deg: angle,
            lambda,
            background: [1e-4, -2e-4],
            spacing_um: 0.05,
        }
    }

    /// The model equals the bead model rendered independently (`render_scene` of a long
    /// straight `Filament` on the same lattice) plus the backgrounds.
    #[test]
    fn line_model_equals_the_bead_model_render() {
        let f = fil(20.0, 0.13, 2.0);
        let (tpl, xs, ev) = eval_on_grid(&f, 41, 0.05);
        // the same sections: t_k = k·h about the foot, far beyond the scan's reach
        let foot = f.foot();
        let t = f.angle_deg.to_radians();
        let (k0, k1) = (-200i64, 200i64);
        let beads: Vec<(f64, f64, f64)> = (k0..=k1)
            .map(|k| {
                let s = k as f64 * 0.05;
                (
                    foot[0] + s * t.sin(),
                    foot[1] + s * t.cos(),
                    f.lambda * 0.05,
                )
            })
            .collect();
        let sc = render_scene(&tpl, &beads, &[], &BeadModelOptions::default(), &xs, &xs).unwrap();
        let mut worst: f64 = 0.0;
        for r in 0..41 {
            for c in 0..41 {
                let i = r * 41 + c;
                let a = ev[0][i][0] - f.background[0];
                let b = sc.sx.data[[r, c]] / tpl.norm_factor;
                worst = worst.max((a - b).abs());
                let a = ev[1][i][0] - f.background[1];
                let b = sc.sy.data[[r, c]] / tpl.norm_factor;
                worst = worst.max((a - b).abs());
            }
        }
        let peak = sc.sx.data.iter().fold(0f64, |m, v| m.max(v.abs()));
        assert!(worst < 1e-12 * peak.max(1.0), "worst {worst}, peak {peak}");
    }

    /// The analytic gradient equals central differences of the model.
    #[test]
    fn line_gradient_matches_central_differences() {
        let f = fil(-35.0, -0.2, 1.5);
        let (tpl, xs, ev) = eval_on_grid(&f, 31, 0.07);
        let p = f.params();
        let steps = [1e-5, 1e-6, 1e-5];
        for (k, &dk) in steps.iter().enumerate() {
            let mut a = p;
            let mut b = p;
            a[k] += dk;
            b[k] -= dk;
            let ea = line_eval(&tpl, &f.with_params(&a), &xs, &xs).unwrap();
            let eb = line_eval(&tpl, &f.with_params(&b), &xs, &xs).unwrap();
            let mut worst: f64 = 0.0;
            let mut scale: f64 = 0.0;
            for ch in 0..2 {
                for i in 0..ev[ch].len() {
                    let num = (ea[ch][i][0] - eb[ch][i][0]) / (2.0 * dk);
                    worst = worst.max((num - ev[ch][i][1 + k]).abs());
                    scale = scale.max(ev[ch][i][1 + k].abs());
                }
            }
            assert!(worst < 1e-5 * scale, "parameter {k}: {worst} of {scale}");
        }
    }

    /// The bound of λ for a filament along y on a symmetric grid, with every other parameter
    /// known, is σ/√Σ(∂μ/∂λ)²; the joint bound is at least that (information about nuisance
    /// parameters only adds variance), and bounds scale as σ (and λ's relative bound as σ/λ).
    #[test]
    fn line_bounds_scale_with_noise_and_dominate_the_single_parameter_bound() {
        let f = fil(0.0, 0.0, 2.0);
        let (tpl, xs, ev) = eval_on_grid(&f, 41, 0.05);
        let sig = 1e-3;
        let s2: f64 = ev.iter().flatten().map(|o| o[3] * o[3]).sum();
        let single = sig / s2.sqrt();
        let b = line_crlb(&tpl, &f, &xs, &xs, &[0, 1], &|_, _, _| Some(sig)).unwrap();
        assert!(
            b.lambda >= single * (1.0 - 1e-12),
            "{} < {single}",
            b.lambda
        );
        let b2 = line_crlb(&tpl, &f, &xs, &xs, &[0, 1], &|_, _, _| Some(2.0 * sig)).unwrap();
        assert!((b2.lambda / b.lambda - 2.0).abs() < 1e-9);
        assert!((b2.angle_deg / b.angle_deg - 2.0).abs() < 1e-9);
        assert!((b.lambda_rel - b.lambda / 2.0).abs() < 1e-15);
        assert!((b.diameter_rel - 0.5 * b.lambda_rel).abs() < 1e-15);
        // along y the filament is invisible in Sy (Sec. 4.2 symmetry): Sx alone carries all
        // the information about λ; at 45° both channels see it and Sx alone bounds worse
        let bx = line_crlb(&tpl, &f, &xs, &xs, &[0], &|_, _, _| Some(sig)).unwrap();
        assert!((bx.lambda / b.lambda - 1.0).abs() < 1e-3, "{bx:?} vs {b:?}");
        assert_eq!(bx.background[1], 0.0);
        let f45 = fil(45.0, 0.0, 2.0);
        let b45 = line_crlb(&tpl, &f45, &xs, &xs, &[0, 1], &|_, _, _| Some(sig)).unwrap();
        let bx45 = line_crlb(&tpl, &f45, &xs, &xs, &[0], &|_, _, _| Some(sig)).unwrap();
        assert!(bx45.lambda > 1.2 * b45.lambda, "{bx45:?} vs {b45:?}");
        assert!(bx45.angle_deg > 1.2 * b45.angle_deg);
        // no filament, no information about where it is
        let e = line_crlb(&tpl, &fil(0.0, 0.0, 0.0), &xs, &xs, &[0, 1], &|_, _, _| {
            Some(sig)
        })
        .unwrap_err()
        .to_string();
        assert!(e.contains("no information about offset"), "{e}");
    }

    /// The misfit limit is the fixed ratio for a full raster and grows for small images, where
    /// the ratio of white noise scatters more (5 standard errors).
    #[test]
    fn misfit_limit_widens_for_small_images() {
        assert_eq!(misfit_limit(2 * 64 * 64), MISFIT_RATIO);
        let strip = misfit_limit(2 * 25 * 10);
        let want = 1.0 + 5.0 * (1.0 / 1000.0 + 1.36 / 500.0f64).sqrt();
        assert!((strip - want).abs() < 1e-12 && strip > 1.3, "{strip}");
    }

    #[test]
    fn weight_per_length_and_volume_round_trip() {
        let tpl = Template::analytic_standin(0.4, 0.02, 1.6).unwrap();
        let n = 1.587;
        let d = 25.0;
        let l = lambda_of_diameter(&tpl, d, n).unwrap();
        let v = volume_per_um(&tpl, l, n).unwrap();
        let want = std::f64::consts::PI * d * d / 4.0 * 1000.0;
        assert!((v / want - 1.0).abs() < 1e-12, "{v} vs {want}");
        let e = volume_per_um(&tpl, l, 1.0).unwrap_err().to_string();
        assert!(e.contains("n_corr = -"), "{e}");
    }
}
