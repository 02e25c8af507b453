//! The beam from the measurement: fit the focused beam and the QPD to one
//! xy scan of a reference bead at the focus (docs/physics.md §10.4).
//!
//! **Model.** The reference bead (a point dipole of polarisability α, the tier the simulator
//! uses for a 110 nm polystyrene bead) at stage position r0 in the aplanatic vector focus of
//! pupil filling f0 (Novotny & Hecht eq. 3.52; `Optics::pupil_filling`), seen by a QPD whose
//! cross is rotated by δ from the polarisation axis and offset by (o_x, o_y) cone radii in the
//! BFP, the beam's polarisation axis at ψ from the stage x axis:
//!
//! ```text
//! Sx(r) = g_x [T_x(r') + δ ∂_δT_x(r')] + g_x o_x ∂_{ox}T_x(r') + b_x
//! Sy(r) = g_y [T_y(r') + δ ∂_δT_y(r')] + g_y o_y ∂_{oy}T_y(r') + b_y
//! Sz(r) = g_z T_z(r') + b_z,              r' = R(−ψ)(r − r0)
//! ```
//!
//! T is the ideal-QPD response of the bead (α × the per-unit-α plane of
//! `optics::mie_template` at z = 0, the simulator's own template), ∂_δT and ∂_oT its changes per
//! degree of QPD rotation and per cone radius of QPD offset (forward differences over
//! [`EPS_ROT_DEG`] and [`EPS_OFFSET`], i.e. the misalignment to first order; an offset moves
//! only its own channel's sign boundary, so one build gives both offset columns). g are the
//! amplifier gains (the signals' units per simulator unit; 1 in the simulator), b the channel
//! offsets. The QPD gain ratio is g_y/g_x (the `misalignment` effect's `gain_y`).
//!
//! **Parameters and identifiability.** Linear (solved exactly for given non-linear ones,
//! variable projection): g_x, g_x·o_x, g_x·z·o_x, b_x, g_y, g_y·o_y, g_y·z·o_y, b_y, g_z, b_z (the
//! z·o terms: off the focus an offset enters at first order, through the mixed derivative
//! ∂²T/∂z∂o, with the sign of z·o). Non-linear, cheap
//! (template interpolation only): x0, y0, ψ, δ and ζ, the bead's height off the model's squared
//! (÷ `EPS_Z_UM`²). Non-linear, expensive (seven template-plane builds per value): v = 1/f0², so the uniformly filled pupil is v = 0 (the model is analytic
//! in v; v < 0, a pupil brighter at its rim, is not physical and is the search's lower bound).
//! One xy scan at the focus sees the focal width (→ v) and the elongation of the vector focus
//! along the polarisation (→ ψ); a QPD rotation δ mixes Sx into Sy and back. δ and ψ are
//! separable only through the focus's ellipticity (for a round focus a rotation of the whole
//! response and a rotation of the QPD are the same thing); their correlation is reported.
//! The fitted QPD angle relative to the stage is ψ + δ. At the focus a QPD offset enters at
//! second order (the bead's interference term is odd across the QPD's dividing line), so o² is
//! measured and o's sign is not; the rotation and offset columns are differences about a
//! misalignment `about` that the fit moves to its answer (relinearisation; docs/physics.md
//! §10.4). A height off the focus enters at second order too, and trades with v (a bead 46 nm
//! off read v 4.3σ high with the height held at zero): its square is fitted, through the bead
//! `EPS_Z_UM` above and below, averaged; beyond [`DEFOCUS_LIN_UM`] the answer is flagged, and
//! [`defocus_test`] refits at heights out to 0.9 µm (a bead far off the focus reads as a smaller
//! pupil filling with a residual at the noise).
//!
//! **Uncertainty.** Weighted least squares with per-channel weights 1/σ_c², σ_c the channel's
//! noise estimated from second differences of the image (robust, independent of the model);
//! the covariance is s²(JᵀJ)⁻¹ with J the Jacobian of all 16 parameters at the optimum (v by
//! a forward difference over two template builds) and s² the weighted residual variance
//! (residual sum / (N − 16)). The answer is refused when it would not mean anything: no bead
//! (the gain g_x below 10 σ), or a residual rms above twice the noise (a scan that is not this
//! bead in this beam: wrong size, wrong kind, out of focus).
//!
//! **The Sz gain is not measurable here.** A non-absorbing point scatterer at the focus (z = 0)
//! scatters a wave in quadrature with the focused field (the Gouy phase), so the total power on
//! the QPD, Sz (suppl. S3, the sum of the four quadrants' δI), does not change to first order
//! in α: Sz is odd in z and zero in the focal plane (axial detection, Pralle et al. 1999, the
//! paper's ref. PralleEL99; the paper itself uses only Sx and Sy). The model plane's Sz at
//! z = 0 is rounding noise (≲ 1e-12 of its Sx), and a free g_z fitted to it came out at
//! ~7e12 ± 9e12: not a gain, a degenerate parameter. So when the model's Sz is below
//! [`SZ_NIL`] × its Sx the Sz bead column is left out (only the offset b_z is fitted, 15
//! parameters) and `gain_z` is `None`, with the reason; when it is present, g_z is reported
//! only when it stands [`GAIN_Z_MIN_SIGMA`] σ clear of zero.

use super::{check_range, AnalysisError, Result};
use crate::data::Image;
use crate::optics::grid::Grid2;
use crate::optics::mie_template::dipole_plane;
use crate::optics::params::{Beam, Optics};
use crate::optics::rayleigh::{alpha_um3, DetectorModel, Misalignment};
use crate::optics::template::TemplateSpec;
use crate::optics::ValidOptics;
use nalgebra::{DMatrix, DVector};
use std::sync::Arc;
use std::time::Instant;

/// QPD rotation (degrees) of the forward difference that gives ∂_δT.
pub const EPS_ROT_DEG: f64 = 2.0;
/// QPD offset (cone radii) of the forward difference that gives ∂_oT.
pub const EPS_OFFSET: f64 = 0.05;
/// Largest v = 1/f0² searched (f0 ≥ 0.5: a pupil filled to half its radius).
pub const V_MAX: f64 = 4.0;
/// The model's Sz counts as absent when its largest value is below this fraction of the largest
/// Sx (at the focus it is rounding noise, ~1e-13 of Sx; any real axial signal is percents).
pub const SZ_NIL: f64 = 1e-6;
/// A fitted Sz gain is reported only this many σ away from zero (below, the data do not
/// determine it: a chance 5σ excursion of noise happens once in 1.7 million fits).
pub const GAIN_Z_MIN_SIGMA: f64 = 5.0;
/// Smallest and largest reference-bead diameter (nm): inside the point dipole's domain
/// (docs/physics.md §10), and large enough to be seen.
pub const D_RANGE_NM: (f64, f64) = (40.0, 200.0);

/// The aligned QPD (no offset, no rotation, equal gains).
pub const ALIGNED: Misalignment = Misalignment {
    offset_x: 0.0,
    offset_y: 0.0,
    rotation_deg: 0.0,
    gain_y: 1.0,
};

/// Options of [`fit_beam`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BeamFitOptions {
    /// Reference bead diameter (nm) and refractive index.
    pub d_nm: f64,
    pub n: f64,
    /// The bead's height in the model, µm (0: the scan at the focus; the defocus test tries
    /// others).
    pub z_um: f64,
    /// The QPD misalignment the model's rotation and offset columns are taken about (the
    /// linearisation point; `fit_beam` starts from the aligned QPD and moves it to its answer).
    pub about: Misalignment,
    /// Template grid of the model planes (the simulator's default).
    pub grid: TemplateSpec,
}

impl Default for BeamFitOptions {
    fn default() -> Self {
        Self {
            d_nm: 110.0,
            n: 1.572,
            z_um: 0.0,
            about: ALIGNED,
            grid: TemplateSpec::default(),
        }
    }
}

/// A fitted value and its 1σ uncertainty.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Value {
    pub value: f64,
    pub sigma: f64,
}

/// The result of [`fit_beam`]. Angles in degrees, positions in µm, offsets in cone radii.
#[derive(Debug, Clone)]
pub struct BeamFit {
    /// v = 1/f0² (0: uniformly filled pupil).
    pub inv_f0_sq: Value,
    /// f0 = 1/√v (∞ when v = 0) and its σ by propagation (f0³σ_v/2).
    pub pupil_filling: Value,
    pub x0: Value,
    pub y0: Value,
    /// Polarisation axis ψ from the stage x axis.
    pub polarization_deg: Value,
    /// QPD rotation δ relative to the polarisation axis (the QPD's angle to the stage is ψ + δ).
    pub qpd_rotation_deg: Value,
    /// The QPD offsets' magnitudes, cone radii: at the focus an offset enters the response at
    /// second order (the bead's interference term is odd across the QPD's dividing line there,
    /// so the line's first-order shift integrates to nothing), and a scan at the focus does
    /// not tell +o from −o. The misalignment effect's images at the focus are the same for
    /// either sign. `offset_*_sq` are the measured squares (their σ holds near zero too).
    pub offset_x: Value,
    pub offset_y: Value,
    pub offset_x_sq: Value,
    pub offset_y_sq: Value,
    /// The bead's height off the model's (`BeamFitOptions::z_um`), squared, µm²: fitted with
    /// the rest, as the curvature of the response in the height (at the focus a height enters
    /// at second order and its sign is not measured). Held free, it widens σ(v), with which it
    /// trades (a bead 46 nm off the focus read v 4.3σ high with the height held at zero).
    /// Linear in the square to `EPS_Z_UM`; beyond, [`BeamFit::defocus`] tests other heights.
    pub defocus_sq: Value,
    pub gain_x: Value,
    pub gain_y: Value,
    /// The Sz gain, when the scan determines it; `None` for a bead at the focus, where Sz
    /// carries no bead signal ([`BeamFit::gain_z_note`] says why).
    pub gain_z: Option<Value>,
    /// Why `gain_z` is `None`.
    pub gain_z_note: Option<String>,
    /// g_y/g_x (the `misalignment` effect's `gain_y`).
    pub gain_ratio: Value,
    /// Channel offsets b (signal units).
    pub background: [f64; 3],
    /// Residual rms and noise estimate per channel (Sx, Sy, Sz), signal units.
    pub residual_rms: [f64; 3],
    pub noise: [f64; 3],
    /// Weighted residual variance s² (≈ 1 when the model explains the scan to the noise).
    pub chi2_red: f64,
    /// Correlation of ψ and δ.
    pub corr_polarization_rotation: f64,
    /// Template-plane builds and wall time of the fit.
    pub builds: usize,
    pub seconds: f64,
    /// The fitted instrument: the optics with `beam: vector` and the fitted pupil filling, and
    /// the QPD misalignment (offsets, rotation ψ + δ relative to the stage axes… as the
    /// simulator's effect takes it: relative to the polarisation, δ; gain_y = g_y/g_x).
    pub optics: Optics,
    pub misalignment: Misalignment,
    /// The test of the model's focus ([`defocus_test`]): the bead height that explains the scan
    /// best among those tried, and by how much better than the model's (Δχ², in units of the
    /// fit's residual variance).
    pub defocus: Defocus,
}

/// What [`defocus_test`] found: `z_um`, the bead height (µm, the model's own convention, as
/// `BeamFitOptions::z_um`) that explains the scan best, and `dchi2`, its χ² below the model's
/// height (0 when the model's height is the best tried).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Defocus {
    pub z_um: f64,
    pub dchi2: f64,
}

/// Δχ² beyond which [`defocus_test`] says the bead is not at the model's height (3σ of one
/// added parameter: a scan at that height exceeds it once in 740).
pub const DEFOCUS_DCHI2: f64 = 9.0;

/// Heights (µm from the model's) up to which [`defocus_test`] tries every step whatever the
/// cost does.
const DEFOCUS_FULL_UM: f64 = 0.6;

/// The heights beside the model's that [`defocus_test`] tries, µm: from
/// [`DEFOCUS_LIN_UM`] out (nearer, the fitted height² says it).
const DEFOCUS_STEPS_UM: [f64; 5] = [0.25, 0.35, 0.5, 0.7, 0.9];

/// The largest height of the bead off the model's, µm, at which the fitted height²
/// (`BeamFit::defocus_sq`, linear in the square with its curvature plane `EPS_Z_UM` = 0.1 µm
/// away, and the height × offset terms linear in the height) holds the other parameters (above
/// it, a warning). In the truth sweep (seed 2026, N = 60) beads within 0.1 µm of the focus read
/// every parameter within 2.1σ; one 0.19 µm off with offsets of 0.1 cone radii read the gain
/// ratio 3.7σ and o_y² 4σ off; one 0.5 µm off (`tests/beam_fit.rs`) read the gain ratio 5σ and
/// o_x² 4.4σ off, and its height² as 0.204 ± 0.003 for 0.25.
pub const DEFOCUS_LIN_UM: f64 = 0.15;

/// The three model planes for one v: ideal QPD, rotated QPD, offset QPD (all through the
/// misaligned-QPD quadrature so that quadrature errors cancel in the differences).
struct Basis {
    g0: Arc<Grid2>,
    grot: Arc<Grid2>,
    goff: Arc<Grid2>,
    /// The bead `EPS_Z_UM` above and below the model's height, averaged: the curvature of the
    /// response in the height (its first-order part, ∝ height × offset, cancels).
    gz: Arc<Grid2>,
    /// The height's first-order term per unit offset, (∂T/∂z)/o, as the secant through o = 0
    /// over the linearisation's offsets ô and ô + `EPS_OFFSET` (at ô = 0, the mixed derivative
    /// ∂²T/∂z∂o): off the focus an offset enters at first order, ∝ z·o, and about an offset QPD
    /// the height does too. Its coefficient per channel is g·z·o, whose sign the scan measures.
    gzo: Arc<Grid2>,
    /// max |Sz| / max |Sx| of the ideal plane: below [`SZ_NIL`] the Sz bead column is left out.
    sz_ratio: f64,
}

impl Basis {
    fn sz_signal(&self) -> bool {
        self.sz_ratio >= SZ_NIL
    }
}

fn plane(
    optics: &ValidOptics,
    grid: TemplateSpec,
    m: Misalignment,
    alpha: f64,
    z_um: f64,
) -> Result<Arc<Grid2>> {
    let detector = DetectorModel {
        polarization: true,
        misalignment: Some(m),
    };
    // the simulator's own point dipole in this beam, per unit α
    let mut g = dipole_plane(optics, detector, grid.h, grid.interp, z_um)?;
    for n in g.data.iter_mut() {
        for c in n.iter_mut() {
            *c *= alpha;
        }
    }
    Ok(Arc::new(g))
}

fn optics_for_v(base: &Optics, v: f64) -> Optics {
    Optics {
        beam: Beam::Vector,
        pupil_filling: if v <= 0.0 {
            f64::INFINITY
        } else {
            1.0 / v.sqrt()
        },
        ..base.clone()
    }
}

/// The model planes for one v at height `z_um`, about `opts.about`; `sz`: the Sz decision to
/// keep (`Data::sz_ratio`), None: this plane's own.
fn basis(
    base: &Optics,
    opts: &BeamFitOptions,
    alpha: f64,
    (v, z_um): (f64, f64),
    sz: Option<f64>,
) -> Result<Basis> {
    let o = ValidOptics::new(optics_for_v(base, v))?;
    let grid = opts.grid;
    let zero = Misalignment {
        gain_y: 1.0,
        ..opts.about
    };
    let g0 = plane(&o, grid, zero, alpha, z_um)?;
    let peak = |c: usize| g0.data.iter().fold(0.0f64, |m, v| m.max(v[c].abs()));
    let sz_ratio = sz.unwrap_or_else(|| peak(2) / peak(0).max(f64::MIN_POSITIVE));
    let up = plane(&o, grid, zero, alpha, z_um + EPS_Z_UM)?;
    let down = plane(&o, grid, zero, alpha, z_um - EPS_Z_UM)?;
    let off = Misalignment {
        offset_x: zero.offset_x + EPS_OFFSET,
        offset_y: zero.offset_y + EPS_OFFSET,
        ..zero
    };
    let up_o = plane(&o, grid, off, alpha, z_um + EPS_Z_UM)?;
    let down_o = plane(&o, grid, off, alpha, z_um - EPS_Z_UM)?;
    let gz = combine(&[&up, &down], |t| {
        std::array::from_fn(|c| 0.5 * (t[0][c] + t[1][c]))
    });
    // the height's first-order term per unit offset, ∂T/∂z / o: odd in o (the image is even
    // under (z, o) → (−z, −o)), so its secant through o = 0, taken over the linearisation's
    // two offsets ô and ô + ε (at ô = 0, the mixed derivative ∂²T/∂z∂o); its coefficient
    // per channel is g·z·o with o the signed offset
    let span = [
        2.0 * zero.offset_x + EPS_OFFSET,
        2.0 * zero.offset_y + EPS_OFFSET,
        1.0,
    ];
    let gzo = combine(&[&up, &down, &up_o, &down_o], |t| {
        std::array::from_fn(|c| {
            ((t[0][c] - t[1][c]) + (t[2][c] - t[3][c])) / (2.0 * EPS_Z_UM * span[c])
        })
    });
    Ok(Basis {
        sz_ratio,
        gz: Arc::new(gz),
        gzo: Arc::new(gzo),
        g0,
        grot: plane(
            &o,
            grid,
            Misalignment {
                rotation_deg: zero.rotation_deg + EPS_ROT_DEG,
                ..zero
            },
            alpha,
            z_um,
        )?,
        goff: plane(
            &o,
            grid,
            Misalignment {
                offset_x: zero.offset_x + EPS_OFFSET,
                offset_y: zero.offset_y + EPS_OFFSET,
                ..zero
            },
            alpha,
            z_um,
        )?,
    })
}

/// Planes combined node by node: `f` of every plane's value at each node of the widest (planes
/// at other heights reach further: their node grids share the spacing and the centre, and a
/// node outside a plane counts as zero there).
fn combine(planes: &[&Grid2], f: impl Fn(&[[f64; 3]]) -> [f64; 3]) -> Grid2 {
    let wide = planes
        .iter()
        .copied()
        .max_by_key(|g| g.nu * g.nv)
        .expect("planes to combine");
    let at = |g: &Grid2, u: f64, v: f64| -> [f64; 3] {
        let i = ((u - g.u0) / g.h).round();
        let j = ((v - g.v0) / g.h).round();
        if i < 0.0 || j < 0.0 || i as usize >= g.nu || j as usize >= g.nv {
            [0.0; 3]
        } else {
            g.data[j as usize * g.nu + i as usize]
        }
    };
    Grid2::from_fn(
        wide.u0,
        wide.v0,
        wide.h,
        wide.nu,
        wide.nv,
        wide.interp,
        |u, v| {
            let vals: Vec<[f64; 3]> = planes.iter().map(|g| at(g, u, v)).collect();
            f(&vals)
        },
    )
}

/// The scan's pixels (finite only) and the data.
struct Data {
    xy: Vec<(f64, f64)>,
    s: [Vec<f64>; 3],
    w: [f64; 3],
    /// The Sz decision of the first model (aligned QPD, the model's height), kept for every
    /// later one: a model linearised about an offset QPD, or at another height, can carry a
    /// trace of Sz that would switch the Sz bead column on with a degenerate gain.
    sz_ratio: Option<f64>,
}

/// Non-linear parameters θ = (x0, y0, ψ rad, δ deg, ζ), ζ = (z − z_model)²/`EPS_Z_UM`²: the
/// bead's height off the model's, squared (at the focus a height enters at second order, as an
/// offset does; the image is even in it for an aligned QPD).
type Theta = [f64; NTH];

/// How many non-linear parameters θ holds.
const NTH: usize = 5;

/// Finite-difference steps of θ (µm, µm, rad, deg, ζ).
const TH_STEPS: Theta = [1e-4, 1e-4, 1e-3, 0.02, 0.01];

/// The height step of the curvature plane (`Basis::gz`), µm: ζ = 1 is a bead this far off the
/// model's height.
const EPS_Z_UM: f64 = 0.1;

/// Indices of the covariance's parameters: θ, then v, then the linear coefficients per channel
/// (gain, offset, height × offset, background; Sz: gain and background, or background alone).
const I_V: usize = NTH;
const I_GX: usize = NTH + 1;
const I_AX: usize = NTH + 2;
const I_GY: usize = NTH + 5;
const I_AY: usize = NTH + 6;
const I_GZ: usize = NTH + 9;

/// Columns of each channel's linear model at θ (per pixel).
fn columns(b: &Basis, d: &Data, th: &Theta) -> [Vec<Vec<f64>>; 3] {
    let (sp, cp) = th[2].sin_cos();
    let n = d.xy.len();
    let mut cx = vec![vec![0.0; n], vec![0.0; n], vec![0.0; n], vec![1.0; n]];
    let mut cy = vec![vec![0.0; n], vec![0.0; n], vec![0.0; n], vec![1.0; n]];
    let sz = b.sz_signal();
    let mut cz = if sz {
        vec![vec![0.0; n], vec![1.0; n]]
    } else {
        vec![vec![1.0; n]]
    };
    for (i, &(x, y)) in d.xy.iter().enumerate() {
        let (dx, dy) = (x - th[0], y - th[1]);
        let (u, v) = (cp * dx + sp * dy, -sp * dx + cp * dy);
        let t0 = b.g0.eval(u, v);
        let tr = b.grot.eval(u, v);
        let to = b.goff.eval(u, v);
        let tz = b.gz.eval(u, v);
        let tzo = b.gzo.eval(u, v);
        let (f, zeta) = (th[3] / EPS_ROT_DEG, th[4]);
        cx[0][i] = t0[0] + f * (tr[0] - t0[0]) + zeta * (tz[0] - t0[0]);
        cx[1][i] = (to[0] - t0[0]) / EPS_OFFSET;
        cx[2][i] = tzo[0];
        cy[0][i] = t0[1] + f * (tr[1] - t0[1]) + zeta * (tz[1] - t0[1]);
        cy[1][i] = (to[1] - t0[1]) / EPS_OFFSET;
        cy[2][i] = tzo[1];
        if sz {
            cz[0][i] = t0[2] + zeta * (tz[2] - t0[2]);
        }
    }
    [cx, cy, cz]
}

/// Least squares of one channel on its columns: coefficients.
fn solve(cols: &[Vec<f64>], s: &[f64]) -> Option<DVector<f64>> {
    let m = cols.len();
    let mut a = DMatrix::<f64>::zeros(m, m);
    let mut r = DVector::<f64>::zeros(m);
    for i in 0..m {
        for j in 0..=i {
            let v: f64 = cols[i].iter().zip(&cols[j]).map(|(p, q)| p * q).sum();
            a[(i, j)] = v;
            a[(j, i)] = v;
        }
        r[i] = cols[i].iter().zip(s).map(|(p, q)| p * q).sum();
    }
    a.cholesky().map(|c| c.solve(&r))
}

/// Weighted residuals (all channels) at θ with the linear parameters solved; and the
/// coefficients per channel.
fn residuals(b: &Basis, d: &Data, th: &Theta) -> Option<(Vec<f64>, [DVector<f64>; 3])> {
    let cols = columns(b, d, th);
    let n = d.xy.len();
    let mut res = Vec::with_capacity(3 * n);
    let mut coef: Vec<DVector<f64>> = Vec::new();
    for c in 0..3 {
        let k = solve(&cols[c], &d.s[c])?;
        for i in 0..n {
            let m: f64 = cols[c]
                .iter()
                .zip(k.iter())
                .map(|(col, kk)| col[i] * kk)
                .sum();
            res.push((d.s[c][i] - m) * d.w[c]);
        }
        coef.push(k);
    }
    let [a, bb, cc]: [DVector<f64>; 3] = coef.try_into().ok()?;
    Some((res, [a, bb, cc]))
}

fn ss(r: &[f64]) -> f64 {
    r.iter().map(|v| v * v).sum()
}

/// Levenberg–Marquardt over θ on the variable-projection residual (numeric Jacobian: each
/// evaluation costs template interpolation only). Returns (θ, residual sum of squares).
fn fit_theta(b: &Basis, d: &Data, mut th: Theta) -> Result<(Theta, f64)> {
    let steps = TH_STEPS;
    let fail = || {
        AnalysisError::Failed(
            "the model could not be evaluated (singular linear system: no signal in a channel?)"
                .into(),
        )
    };
    let (mut r, _) = residuals(b, d, &th).ok_or_else(fail)?;
    let mut cost = ss(&r);
    let mut lambda = 1e-3;
    for _ in 0..40 {
        let mut jac = Vec::with_capacity(NTH);
        for p in 0..NTH {
            let mut tp = th;
            tp[p] += steps[p];
            let (rp, _) = residuals(b, d, &tp).ok_or_else(fail)?;
            jac.push(
                rp.iter()
                    .zip(&r)
                    .map(|(a, c)| (a - c) / steps[p])
                    .collect::<Vec<_>>(),
            );
        }
        let mut jtj = nalgebra::SMatrix::<f64, NTH, NTH>::zeros();
        let mut jtr = nalgebra::SVector::<f64, NTH>::zeros();
        for i in 0..NTH {
            for j in 0..NTH {
                jtj[(i, j)] = jac[i].iter().zip(&jac[j]).map(|(p, q)| p * q).sum();
            }
            jtr[i] = jac[i].iter().zip(&r).map(|(p, q)| p * q).sum();
        }
        let mut improved = false;
        for _ in 0..10 {
            let mut a = jtj;
            for i in 0..NTH {
                a[(i, i)] *= 1.0 + lambda;
            }
            let Some(step) = a.lu().solve(&(-jtr)) else {
                lambda *= 10.0;
                continue;
            };
            let mut tn = th;
            for i in 0..NTH {
                tn[i] += step[i];
            }
            if let Some((rn, _)) = residuals(b, d, &tn) {
                let cn = ss(&rn);
                if cn < cost {
                    let rel = (cost - cn) / cost.max(1e-300);
                    th = tn;
                    r = rn;
                    cost = cn;
                    lambda = (lambda / 10.0).max(1e-9);
                    improved = true;
                    if rel < 1e-10 {
                        return Ok((th, cost));
                    }
                    break;
                }
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    Ok((th, cost))
}

/// Robust per-channel noise: 1.4826·MAD of the second differences along x, / √6.
fn noise_of(img: &Image) -> f64 {
    let (ny, nx) = img.shape();
    let mut d = Vec::new();
    for i in 0..ny {
        for j in 1..nx.saturating_sub(1) {
            let v = img.data[(i, j - 1)] - 2.0 * img.data[(i, j)] + img.data[(i, j + 1)];
            if v.is_finite() {
                d.push(v.abs());
            }
        }
    }
    if d.is_empty() {
        return f64::NAN;
    }
    d.sort_by(|a, b| a.total_cmp(b));
    1.4826 * d[d.len() / 2] / 6f64.sqrt()
}

/// Initial bead position: midpoint between the Sx maximum and minimum (x) and between the Sy
/// maximum and minimum (y).
fn initial_position(sx: &Image, sy: &Image) -> (f64, f64) {
    let arg = |img: &Image, sign: f64| {
        let mut best = (f64::NEG_INFINITY, 0.0, 0.0);
        for ((i, j), &v) in img.data.indexed_iter() {
            if v.is_finite() && sign * v > best.0 {
                best = (sign * v, img.x[j], img.y[i]);
            }
        }
        (best.1, best.2)
    };
    let (a, b) = (arg(sx, 1.0), arg(sx, -1.0));
    let (c, e) = (arg(sy, 1.0), arg(sy, -1.0));
    (0.5 * (a.0 + b.0), 0.5 * (c.1 + e.1))
}

/// Refuse a bead, a scan or images `fit_beam` cannot fit, naming the argument and the
/// allowed range.
fn check_beam_inputs(
    optics: &Optics,
    sx: &Image,
    sy: &Image,
    sz: &Image,
    opts: &BeamFitOptions,
) -> Result<()> {
    check_range("d_nm", opts.d_nm, D_RANGE_NM.0, D_RANGE_NM.1)?;
    check_range("n", opts.n, 1.0, 3.0)?;
    check_range("z", opts.z_um, -3.0, 3.0)?;
    if (opts.n - optics.n_medium).abs() < 0.02 {
        return Err(AnalysisError::OutOfRange {
            name: "n",
            value: opts.n,
            allowed: format!(
                "|n − n_medium| ≥ 0.02 (n_medium = {}): the bead must scatter",
                optics.n_medium
            ),
        });
    }
    if sx.x_name != "x" || sx.y_name != "y" {
        return Err(AnalysisError::BadInput {
            name: "scan",
            reason: format!(
                "an xy scan at the focus is needed; this one is a {}{} scan",
                sx.x_name, sx.y_name
            ),
        });
    }
    let (ny, nx) = sx.shape();
    if nx < 16 || ny < 16 {
        return Err(AnalysisError::BadInput {
            name: "scan",
            reason: format!("{nx} × {ny} pixels: at least 16 × 16 are needed"),
        });
    }
    let (hx, hy) = (sx.dx().abs(), sx.dy().abs());
    let span = ((nx - 1) as f64 * hx).min((ny - 1) as f64 * hy);
    if !(hx <= 0.1 && hy <= 0.1 && span >= 1.2) {
        return Err(AnalysisError::BadInput {
            name: "scan",
            reason: format!(
                "pixels {hx:.3} × {hy:.3} µm over {span:.2} µm: the fit needs pixels ≤ 0.1 µm and a field ≥ 1.2 µm wide around the bead"
            ),
        });
    }
    for (name, img) in [("sy", sy), ("sz", sz)] {
        if img.shape() != sx.shape() {
            return Err(AnalysisError::BadInput {
                name,
                reason: format!("shape {:?} differs from sx {:?}", img.shape(), sx.shape()),
            });
        }
    }
    Ok(())
}

/// The finite pixels of the three channels, each weighted by 1/σ of its noise (a
/// noiseless scan: 1e-6 of its range as the floor), with the noise and the range per channel.
fn weighted_pixels(sx: &Image, sy: &Image, sz: &Image) -> Result<(Data, [f64; 3], [f64; 3])> {
    let noise = [noise_of(sx), noise_of(sy), noise_of(sz)];
    for (c, &s) in noise.iter().enumerate() {
        if !(s.is_finite()) {
            return Err(AnalysisError::BadInput {
                name: "scan",
                reason: format!("channel {} has no finite pixels", ["sx", "sy", "sz"][c]),
            });
        }
    }
    // weights: 1/σ_c (a noiseless scan: 1e-6 of the channel's range as its floor)
    let mut w = [0.0; 3];
    let mut range = [0.0; 3];
    for (c, img) in [sx, sy, sz].iter().enumerate() {
        let (lo, hi) = (img.min().unwrap_or(0.0), img.max().unwrap_or(0.0));
        range[c] = (hi - lo).max(1e-300);
        w[c] = 1.0 / noise[c].max(1e-6 * range[c]);
    }
    let mut xy = Vec::new();
    let mut s: [Vec<f64>; 3] = [Vec::new(), Vec::new(), Vec::new()];
    for ((i, j), &v) in sx.data.indexed_iter() {
        let (a, b) = (sy.data[(i, j)], sz.data[(i, j)]);
        if v.is_finite() && a.is_finite() && b.is_finite() {
            xy.push((sx.x[j], sx.y[i]));
            s[0].push(v);
            s[1].push(a);
            s[2].push(b);
        }
    }
    let n = xy.len();
    if n < 200 {
        return Err(AnalysisError::BadInput {
            name: "scan",
            reason: format!("{n} finite pixels: at least 200 are needed"),
        });
    }
    Ok((
        Data {
            xy,
            s,
            w,
            sz_ratio: None,
        },
        noise,
        range,
    ))
}

/// The fit's cost profile over the pupil's v = 1/f0²: θ fitted at a coarse set of v, then
/// the minimum refined by parabolas (each v warm-started from the nearest one done). The
/// bases built and the profile (v, cost, θ) are returned; `builds` counts the templates.
#[allow(clippy::type_complexity)]
fn profile_over_v(
    optics: &Optics,
    opts: &BeamFitOptions,
    alpha: f64,
    (sx, sy): (&Image, &Image),
    data: &Data,
    start: Option<(f64, Theta)>,
    builds: &mut usize,
) -> Result<(Vec<(f64, Basis)>, Vec<(f64, f64, Theta)>)> {
    let (x0, y0) = initial_position(sx, sy);
    let mut theta: Theta = start.map_or([x0, y0, 0.0, 0.0, 0.0], |s| s.1);
    let mut bases: Vec<(f64, Basis)> = Vec::new();
    let mut profile: Vec<(f64, f64, Theta)> = Vec::new();
    let mut eval_v = |v: f64,
                      theta: &mut Theta,
                      bases: &mut Vec<(f64, Basis)>,
                      profile: &mut Vec<(f64, f64, Theta)>|
     -> Result<f64> {
        let b = basis(optics, opts, alpha, (v, opts.z_um), data.sz_ratio)?;
        *builds += BUILDS_PER_BASIS;
        // warm start from the nearest evaluated v
        let start = profile
            .iter()
            .min_by(|a, b| (a.0 - v).abs().total_cmp(&(b.0 - v).abs()))
            .map(|p| p.2)
            .unwrap_or(*theta);
        let (th, cost) = fit_theta(&b, data, start)?;
        *theta = th;
        bases.push((v, b));
        profile.push((v, cost, th));
        Ok(cost)
    };
    // coarse profile over v (or three points about a previous answer), then parabolic
    // refinement of its minimum
    let coarse = match start {
        None => vec![0.0, 0.5, 1.0, 2.0],
        Some((v0, _)) => {
            let h = 0.1 * v0.max(0.2);
            let mut c = vec![(v0 - h).max(0.0), v0, (v0 + h).min(V_MAX)];
            c.dedup();
            c
        }
    };
    for v in coarse {
        eval_v(v, &mut theta, &mut bases, &mut profile)?;
    }
    for _ in 0..12 {
        let mut p = profile.clone();
        p.sort_by(|a, b| a.0.total_cmp(&b.0));
        let k = (0..p.len())
            .min_by(|&a, &b| p[a].1.total_cmp(&p[b].1))
            .unwrap_or(0);
        let next = if k == p.len() - 1 {
            // minimum at the largest v done: go further out, up to the bound (at the bound
            // there is no neighbour beyond it: the answer stays there and is flagged)
            if p[k].0 >= V_MAX {
                break;
            }
            if k > 0 {
                (p[k].0 + 2.0 * (p[k].0 - p[k - 1].0)).min(V_MAX)
            } else {
                (2.0 * p[k].0).clamp(0.5, V_MAX)
            }
        } else if k == 0 {
            // minimum at the bound v = 0 (uniform pupil) or just above it
            if p.len() > 1 && p[0].0 == 0.0 {
                let v1 = p[1].0;
                if v1 < 0.02 {
                    break;
                }
                0.25 * v1
            } else if p.len() > 1 {
                // a profile started about a previous answer: step down
                (p[0].0 - 2.0 * (p[1].0 - p[0].0)).max(0.0)
            } else {
                break;
            }
        } else {
            let (a, b, c) = (p[k - 1], p[k], p[k + 1]);
            let den = (b.0 - a.0) * (b.1 - c.1) - (b.0 - c.0) * (b.1 - a.1);
            let num = (b.0 - a.0).powi(2) * (b.1 - c.1) - (b.0 - c.0).powi(2) * (b.1 - a.1);
            let vn = if den.abs() > 0.0 {
                b.0 - 0.5 * num / den
            } else {
                b.0
            };
            let vn = vn.clamp(a.0, c.0);
            let tol = V_TOL_REL * b.0.max(0.05);
            if p.iter().any(|q| (q.0 - vn).abs() < tol) {
                // The vertex lands on a point already fitted. Through tight neighbours that is
                // the minimum; through a coarse bracket (1, 2, 4) it can be a grid point that
                // the parabola happens to hit (seed 7: v 2.000 for 1.988, 4.3σ). Bracket it
                // closely on both sides before accepting it.
                let (left, right) = (b.0 - a.0, c.0 - b.0);
                let wide = BRACKET_TOLS * tol;
                if left <= wide && right <= wide {
                    break;
                }
                if left > wide && (vn <= b.0 || right <= wide) {
                    b.0 - (0.05 * left).max(2.0 * tol)
                } else {
                    b.0 + (0.05 * right).max(2.0 * tol)
                }
            } else {
                vn
            }
        };
        eval_v(next, &mut theta, &mut bases, &mut profile)?;
    }
    Ok((bases, profile))
}

/// The covariance of all 16 parameters from the Jacobian at the optimum (central
/// differences in θ, a forward one in v over `b2`, built `dv` away; the linear columns as they
/// are), scaled by the reduced χ²; with the residuals, the linear coefficients and χ².
#[allow(clippy::type_complexity)]
fn covariance(
    b: &Basis,
    b2: &Basis,
    dv: f64,
    data: &Data,
    th_hat: &Theta,
) -> Result<(DMatrix<f64>, Vec<f64>, [DVector<f64>; 3], f64)> {
    let n = data.xy.len();
    let fail = || AnalysisError::Failed("the model could not be evaluated".into());
    let (r0, coef) = residuals(b, data, th_hat).ok_or_else(fail)?;
    // full model as a function of all 16 parameters: p = [x0, y0, ψ, δ, ζ, v, gx, ax, kx, bx, gy, ay, ky, by, gz, bz]
    let model = |b: &Basis, th: &Theta, k: &[DVector<f64>; 3]| -> Vec<f64> {
        let cols = columns(b, data, th);
        let mut out = Vec::with_capacity(3 * n);
        for c in 0..3 {
            for i in 0..n {
                let m: f64 = cols[c]
                    .iter()
                    .zip(k[c].iter())
                    .map(|(col, kk)| col[i] * kk)
                    .sum();
                out.push(m * data.w[c]);
            }
        }
        out
    };
    let m0 = model(b, th_hat, &coef);
    let mut jac: Vec<Vec<f64>> = Vec::new();
    let steps = TH_STEPS;
    for p in 0..NTH {
        let mut tp = *th_hat;
        let mut tm = *th_hat;
        tp[p] += steps[p];
        tm[p] -= steps[p];
        let (a, c) = (model(b, &tp, &coef), model(b, &tm, &coef));
        jac.push(
            a.iter()
                .zip(&c)
                .map(|(a, c)| (a - c) / (2.0 * steps[p]))
                .collect(),
        );
    }
    let m2 = model(b2, th_hat, &coef);
    jac.push(m2.iter().zip(&m0).map(|(a, c)| (a - c) / dv).collect());
    let cols = columns(b, data, th_hat);
    for c in 0..3 {
        for col in &cols[c] {
            let mut j = vec![0.0; 3 * n];
            for i in 0..n {
                j[c * n + i] = col[i] * data.w[c];
            }
            jac.push(j);
        }
    }
    let np = jac.len();
    let mut jtj = DMatrix::<f64>::zeros(np, np);
    for i in 0..np {
        for j in 0..=i {
            let v: f64 = jac[i].iter().zip(&jac[j]).map(|(p, q)| p * q).sum();
            jtj[(i, j)] = v;
            jtj[(j, i)] = v;
        }
    }
    let dof = (3 * n - np) as f64;
    let s2 = ss(&r0) / dof;
    let cov = jtj.try_inverse().ok_or_else(|| {
        AnalysisError::Failed("the parameters are degenerate on this scan (JᵀJ singular)".into())
    })? * s2;
    Ok((cov, r0, coef, s2))
}

/// Refuse an answer that means nothing: no bead (the Sx gain within 10σ of zero), or a
/// channel whose residual is well above its noise (not this bead in this beam).
fn refuse_meaningless(
    gx: f64,
    sd_gx: f64,
    rms: &[f64; 3],
    noise: &[f64; 3],
    range: &[f64; 3],
    opts: &BeamFitOptions,
) -> Result<()> {
    if !(gx.abs() > 10.0 * sd_gx) || !(gx > 0.0) {
        return Err(AnalysisError::Failed(format!(
            "no bead in the scan: the Sx gain {gx:.3e} ± {:.1e} is not ≥ 10σ above zero (is there a reference bead within the field, at the focus?)",
            sd_gx
        )));
    }
    // the relative floor against the largest channel's range: a noise-free scan's Sz is
    // rounding noise on both sides (its residual 2e-19 against a "noise" of 1e-20 refused a
    // noise-free bead)
    let top = range.iter().copied().fold(0.0, f64::max);
    for c in 0..3 {
        if rms[c] > 2.0 * noise[c] && rms[c] > 5e-4 * range[c].max(top) {
            return Err(AnalysisError::Failed(format!(
                "the scan does not look like a {} nm bead (n = {}) at the focus in this beam: the {} residual rms {:.3e} is {:.1}× the channel's noise {:.3e} (allowed ≤ 2×, or ≤ 0.05 % of the largest channel's range); check d_nm, n, the focus and the optics (λ, NA)",
                opts.d_nm,
                opts.n,
                ["sx", "sy", "sz"][c],
                rms[c],
                rms[c] / noise[c],
                noise[c]
            )));
        }
    }
    Ok(())
}

/// The Sz gain when the scan determines it, else why not (`sd_gz`: its σ).
fn gain_z(b: &Basis, coef: &[DVector<f64>; 3], sd_gz: f64) -> (Option<Value>, Option<String>) {
    let val = |value: f64, sigma: f64| Value { value, sigma };
    if !b.sz_signal() {
        (
            None,
            Some(format!(
                "not determined: a bead at the focus changes the total power Sz by nothing (the model's Sz is {:.0e} of its Sx; suppl. S3: the scattered wave is in quadrature with the focus at z = 0); the Sz gain needs a scan off the focus",
                b.sz_ratio
            )),
        )
    } else if coef[2][0].abs() < GAIN_Z_MIN_SIGMA * sd_gz {
        (
            None,
            Some(format!(
                "not determined: the fitted Sz gain {:.3e} ± {:.1e} is within {GAIN_Z_MIN_SIGMA}σ of zero",
                coef[2][0],
                sd_gz
            )),
        )
    } else {
        (Some(val(coef[2][0], sd_gz)), None)
    }
}

/// Fit the beam (pupil filling, polarisation axis) and the QPD (gains, rotation, offsets) to
/// one xy scan of a reference bead at the focus: (sx, sy, sz) on a common grid, axes in µm.
/// `optics` gives λ, n_medium, NA (condenser and objective) and the quadrature; its beam and
/// pupil filling are what is fitted. Module docs for the model, identifiability and the
/// uncertainty; errors name the argument and the allowed range.
pub fn fit_beam(
    optics: &Optics,
    sx: &Image,
    sy: &Image,
    sz: &Image,
    opts: &BeamFitOptions,
) -> Result<BeamFit> {
    let t_start = Instant::now();
    check_beam_inputs(optics, sx, sy, sz, opts)?;
    let alpha = alpha_um3(opts.d_nm, opts.n, optics.n_medium);
    let (mut data, noise, range) = weighted_pixels(sx, sy, sz)?;
    let n = data.xy.len();
    let mut builds = 0usize;
    // the model linearised about the aligned QPD, then about each answer in turn: the rotation
    // and the offsets enter the response non-linearly (an offset at second order at the focus)
    let mut o = *opts;
    let mut st = stage(optics, &o, alpha, (sx, sy), &data, None, &mut builds)?;
    data.sz_ratio = Some(st.b.sz_ratio);
    for _ in 0..MAX_RELINEARISE {
        let next = st.next_about(&o);
        let moved = (next.rotation_deg - o.about.rotation_deg).abs() > 0.05
            || (next.offset_x - o.about.offset_x).abs() > 0.002
            || (next.offset_y - o.about.offset_y).abs() > 0.002;
        if !moved {
            break;
        }
        o.about = next;
        // warm: v about the last answer, θ there with the rotation now in `about`
        let mut th = st.th_hat;
        th[3] = 0.0;
        st = stage(
            optics,
            &o,
            alpha,
            (sx, sy),
            &data,
            Some((st.v_hat, th)),
            &mut builds,
        )?;
    }
    let (v_hat, cost_hat, th_hat, s2) = (st.v_hat, st.cost_hat, st.th_hat, st.s2);
    let (b, cov, r0, coef) = (&st.b, &st.cov, &st.r0, &st.coef);
    let sd = |i: usize| cov[(i, i)].max(0.0).sqrt();
    let val = |value: f64, sigma: f64| Value { value, sigma };
    // parameter indices: 0 x0, 1 y0, 2 ψ, 3 δ, 4 ζ, then I_V, I_GX … (without the Sz bead
    // column, I_GZ is Sz's background)
    let (gx, gy) = (coef[0][0], coef[1][0]);
    let ratio = gy / gx;
    let var_ratio = ratio
        * ratio
        * (cov[(I_GY, I_GY)] / (gy * gy) + cov[(I_GX, I_GX)] / (gx * gx)
            - 2.0 * cov[(I_GX, I_GY)] / (gx * gy));
    let [osq_x, osq_y] = st.offsets_sq(&o);
    // the height model's systematic on o² (the height × offset terms beyond first order)
    let z_abs = th_hat[4].max(0.0).sqrt() * EPS_Z_UM;
    let sys = |q: Value| Value {
        sigma: q
            .sigma
            .hypot(OFFSET_SQ_SYS_PER_UM * z_abs * q.value.max(0.0)),
        ..q
    };
    let (osq_x, osq_y) = (sys(osq_x), sys(osq_y));
    let sv = sd(I_V).hypot(0.5 * V_TOL_REL * v_hat.max(0.05));
    let f0 = if v_hat > 0.0 {
        1.0 / v_hat.sqrt()
    } else {
        f64::INFINITY
    };
    let sf0 = if v_hat > 0.0 {
        0.5 * f0.powi(3) * sv
    } else {
        f64::INFINITY
    };
    // residual rms per channel (signal units)
    let mut rms = [0.0; 3];
    for c in 0..3 {
        rms[c] = (ss(&r0[c * n..(c + 1) * n]) / n as f64).sqrt() / data.w[c];
    }
    refuse_meaningless(gx, sd(I_GX), &rms, &noise, &range, opts)?;
    let defocus = defocus_test(
        optics,
        &o,
        alpha,
        &data,
        (v_hat, cost_hat, th_hat),
        &mut builds,
    )?;
    let psi_deg = th_hat[2].to_degrees();
    let (gain_z, gain_z_note) = gain_z(b, coef, sd(I_GZ));
    let rotation = o.about.rotation_deg + th_hat[3];
    let magnitude = |q: Value| {
        // σ of √q: σ_q/(2√q), and no less than √σ_q where q is within 2σ of zero (there the
        // magnitude is known only to lie below √(q + 2σ_q))
        let m = q.value.max(0.0).sqrt();
        let near_zero = if q.value < 2.0 * q.sigma {
            q.sigma.sqrt()
        } else {
            0.0
        };
        let s = if m > 0.0 { q.sigma / (2.0 * m) } else { 0.0 };
        val(m, s.max(near_zero))
    };
    let fitted = optics_for_v(optics, v_hat);
    Ok(BeamFit {
        inv_f0_sq: val(v_hat, sv),
        pupil_filling: val(f0, sf0),
        x0: val(th_hat[0], sd(0).hypot(POSITION_SYS_UM)),
        y0: val(th_hat[1], sd(1).hypot(POSITION_SYS_UM)),
        polarization_deg: val(psi_deg, sd(2).to_degrees()),
        qpd_rotation_deg: val(rotation, sd(3)),
        offset_x: magnitude(osq_x),
        offset_y: magnitude(osq_y),
        offset_x_sq: osq_x,
        offset_y_sq: osq_y,
        defocus_sq: val(th_hat[4] * EPS_Z_UM * EPS_Z_UM, sd(4) * EPS_Z_UM * EPS_Z_UM),
        gain_x: val(gx, sd(I_GX)),
        gain_y: val(gy, sd(I_GY)),
        gain_z,
        gain_z_note,
        gain_ratio: val(ratio, var_ratio.max(0.0).sqrt()),
        background: [coef[0][3], coef[1][3], coef[2][coef[2].len() - 1]],
        residual_rms: rms,
        noise,
        chi2_red: s2,
        corr_polarization_rotation: cov[(2, 3)] / (sd(2) * sd(3)).max(1e-300),
        builds,
        seconds: t_start.elapsed().as_secs_f64(),
        misalignment: Misalignment {
            offset_x: osq_x.value.max(0.0).sqrt(),
            offset_y: osq_y.value.max(0.0).sqrt(),
            rotation_deg: rotation,
            gain_y: ratio,
        },
        optics: fitted,
        defocus,
    })
}

/// The profile over v stops where its next point would lie within this fraction of v (at
/// least of 0.05) of one already fitted; the best point is the answer, so half of it is a
/// systematic of v (in quadrature with the statistical σ).
const V_TOL_REL: f64 = 3e-4;

/// Template planes built per basis (`basis`): the aligned QPD, the rotated one, the offset
/// one, and the bead above and below the model's height with the QPD aligned and offset.
const BUILDS_PER_BASIS: usize = 7;
/// The profile's vertex is accepted on a fitted point only when both its neighbours lie within
/// this many tolerances of it (otherwise it is bracketed more closely first).
const BRACKET_TOLS: f64 = 40.0;

/// The largest offset (cone radii) the model is linearised about (the QPD's cross must stay
/// inside the beam, |offset| < 0.95; a QPD offset by a third of the cone is far out of
/// alignment).
const MAX_ABOUT_OFFSET: f64 = 0.35;

/// The bead position's systematic, µm, in quadrature with its σ: noise-free scans of seven
/// truth-sweep scenes (20–75 nm pixels, QPDs aligned and misaligned) put the bead within
/// 0.1 nm, and one 5 nm off the focus with offsets of 0.1 cone radii read 0.16 nm off at
/// 1.8× the paper's noise where σ said 0.04 nm (4.4σ, seed 2026).
const POSITION_SYS_UM: f64 = 2e-4;

/// The offsets' squares' systematic per µm of the bead's height off the model's, relative to
/// o², in quadrature with their σ: the height × offset terms are modelled to first order in
/// the height and as odd and linear in o, and beyond that o² reads off by up to
/// 0.15–0.3·|z|·o² (noise-free replays of a 149 nm bead 54–100 nm off the focus with offsets of
/// 0.07–0.124, v 0 and 1, signs of z·o both ways; at 0.25× the paper's noise with 20 nm pixels
/// one read o_y² 6.6σ off, truth sweep seed 2026).
const OFFSET_SQ_SYS_PER_UM: f64 = 0.3;

/// Linearisations of the misalignment after the first (each a profile over v about the last
/// answer).
const MAX_RELINEARISE: usize = 3;

/// One fit of the model linearised about `opts.about`: the best v over the profile, its cost
/// and θ, the basis there, the covariance of all parameters, the residuals, the linear
/// coefficients and s².
struct Stage {
    v_hat: f64,
    cost_hat: f64,
    th_hat: Theta,
    b: Basis,
    cov: DMatrix<f64>,
    r0: Vec<f64>,
    coef: [DVector<f64>; 3],
    s2: f64,
}

impl Stage {
    /// o² of each offset with its σ. About ô the offset column is (T(ô+ε) − T(ô))/ε, which
    /// under the second-order response T(o) = T(0) + o²Q is (2ô + ε)Q; its coefficient
    /// c = a/g is (o² − ô²)/(2ô + ε), so o² = ô² + c(2ô + ε) (c's σ by propagation through a/g).
    fn offsets_sq(&self, opts: &BeamFitOptions) -> [Value; 2] {
        let (cov, coef) = (&self.cov, &self.coef);
        let one = |ch: usize, ig: usize, ia: usize, about: f64| {
            let (g, a) = (coef[ch][0], coef[ch][1]);
            let c = a / g;
            let var_c = c
                * c
                * (cov[(ia, ia)] / (a * a).max(1e-300) + cov[(ig, ig)] / (g * g)
                    - 2.0 * cov[(ig, ia)] / (a * g).abs().max(1e-300) * (a * g).signum());
            let k = 2.0 * about + EPS_OFFSET;
            Value {
                value: about * about + c * k,
                sigma: var_c.max(0.0).sqrt() * k,
            }
        };
        [
            one(0, I_GX, I_AX, opts.about.offset_x),
            one(1, I_GY, I_AY, opts.about.offset_y),
        ]
    }

    /// The next linearisation point: the rotation and the offsets' magnitudes of this fit.
    fn next_about(&self, opts: &BeamFitOptions) -> Misalignment {
        let [qx, qy] = self.offsets_sq(opts);
        // (a noisy o² can exceed what the QPD allows; the model is taken about at most
        // MAX_ABOUT_OFFSET, and the answer is still ô + Δo)
        let o = |q: Value| q.value.max(0.0).sqrt().min(MAX_ABOUT_OFFSET);
        Misalignment {
            offset_x: o(qx),
            offset_y: o(qy),
            rotation_deg: opts.about.rotation_deg + self.th_hat[3],
            gain_y: 1.0,
        }
    }
}

/// The profile over v of the model about `opts.about`, and the covariance at its best v.
fn stage(
    optics: &Optics,
    opts: &BeamFitOptions,
    alpha: f64,
    (sx, sy): (&Image, &Image),
    data: &Data,
    start: Option<(f64, Theta)>,
    builds: &mut usize,
) -> Result<Stage> {
    let (mut bases, profile) = profile_over_v(optics, opts, alpha, (sx, sy), data, start, builds)?;
    let (v_hat, cost_hat, th_hat) = *profile
        .iter()
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .expect("profile has entries");
    let bi = bases
        .iter()
        .position(|(v, _)| *v == v_hat)
        .expect("basis of the best v");
    // Jacobian in v: forward difference (backward at V_MAX) over a new build
    let hv = 0.05 * v_hat.max(0.2);
    let v2 = if v_hat + hv <= V_MAX {
        v_hat + hv
    } else {
        v_hat - hv
    };
    // the same columns as at the optimum (the Sz bead column in or out)
    let b2 = basis(
        optics,
        opts,
        alpha,
        (v2, opts.z_um),
        Some(bases[bi].1.sz_ratio),
    )?;
    *builds += BUILDS_PER_BASIS;
    let b = bases.swap_remove(bi).1;
    let (cov, r0, coef, s2) = covariance(&b, &b2, v2 - v_hat, data, &th_hat)?;
    Ok(Stage {
        v_hat,
        cost_hat,
        th_hat,
        b,
        cov,
        r0,
        coef,
        s2,
    })
}

/// Is the bead at the model's height (`opts.z_um`, 0: the focus)? One xy scan cannot tell a
/// bead 0.5 µm off the focus from a beam of smaller pupil filling at the focus by its residual
/// alone (at 3.9× the paper's noise such a scan fitted v = 1.06 ± 0.03 for 0.43, χ²/ν 0.94, and
/// offsets of 1.6 cone radii for 0.07). The model is refitted at heights `DEFOCUS_STEPS_UM`
/// beside the model's, v re-profiled at each (three builds about the last height's best v, a
/// fourth where the minimum is at an end, one more at the parabola's vertex), until the best cost has risen twice in a row; the
/// χ² gained, in units of the residual variance at the model's height, is returned with the
/// height that gained it. A bead off the focus by ±z and a QPD offset ±o fit alike (the image
/// is even under (z, o) → (−z, −o)); both sides are tried.
fn defocus_test(
    optics: &Optics,
    opts: &BeamFitOptions,
    alpha: f64,
    data: &Data,
    (v_hat, cost_hat, th_hat): (f64, f64, Theta),
    builds: &mut usize,
) -> Result<Defocus> {
    let n = data.xy.len() as f64;
    let s2 = cost_hat / (3.0 * n - (I_GZ + 2) as f64).max(1.0);
    let mut best = Defocus {
        z_um: opts.z_um,
        dchi2: 0.0,
    };
    if !(s2 > 0.0) {
        return Ok(best);
    }
    // both sides: the model's offsets are taken about +|o| (their sign is not measured at the
    // focus), and (z, o) fits as (−z, −o), so a bead at −z with offsets +o shows only on
    // one side
    let sides: &[f64] = &[1.0, -1.0];
    // off the focus an offset enters at first order (∝ z·o): the offsets' columns are taken
    // about the aligned QPD there (taken about the focus's |ô|, which a defocused scan makes
    // large, the columns could not reach a small offset of either sign)
    let opts = &BeamFitOptions {
        about: Misalignment {
            offset_x: 0.0,
            offset_y: 0.0,
            ..opts.about
        },
        ..*opts
    };
    for &side in sides {
        let (mut v, mut th) = (v_hat, th_hat);
        let (mut last, mut rises) = (cost_hat, 0);
        for dz in DEFOCUS_STEPS_UM {
            let z = opts.z_um + side * dz;
            if z.abs() > 3.0 {
                break;
            }
            let mut at = |v: f64, th: Theta| -> Result<(f64, Theta)> {
                let b = basis(optics, opts, alpha, (v, z), data.sz_ratio)?;
                *builds += BUILDS_PER_BASIS;
                let (t, c) = fit_theta(&b, data, th)?;
                Ok((c, t))
            };
            let h = 0.2 * v.max(0.3);
            let vs = [(v - h).max(0.0), v, (v + h).min(V_MAX)];
            let mut pts: Vec<(f64, f64, Theta)> = Vec::with_capacity(5);
            for &vv in &vs {
                let (c, t) = at(vv, th)?;
                pts.push((vv, c, t));
            }
            let k = (0..3)
                .min_by(|&a, &b| pts[a].1.total_cmp(&pts[b].1))
                .unwrap_or(1);
            if k != 1 {
                // the minimum at an end: one step further that way (within [0, V_MAX])
                let vv = (pts[k].0 + if k == 0 { -2.0 * h } else { 2.0 * h }).clamp(0.0, V_MAX);
                if vv != pts[k].0 {
                    let (c, t) = at(vv, pts[k].2)?;
                    pts.push((vv, c, t));
                }
            }
            // then the vertex of the parabola through the best point and its neighbours in v
            // (a height's best v moves by ~0.25 per 0.1 µm: the three points alone missed it,
            // and the cost along the heights rose where v lagged)
            pts.sort_by(|a, b| a.0.total_cmp(&b.0));
            let k = (0..pts.len())
                .min_by(|&a, &b| pts[a].1.total_cmp(&pts[b].1))
                .unwrap_or(0);
            if k > 0 && k + 1 < pts.len() {
                let (a, b, c) = (pts[k - 1], pts[k], pts[k + 1]);
                let den = (b.0 - a.0) * (b.1 - c.1) - (b.0 - c.0) * (b.1 - a.1);
                let num = (b.0 - a.0).powi(2) * (b.1 - c.1) - (b.0 - c.0).powi(2) * (b.1 - a.1);
                if den.abs() > 0.0 {
                    let vv = (b.0 - 0.5 * num / den).clamp(a.0, c.0);
                    if (vv - b.0).abs() > 1e-3 * b.0.max(0.05) {
                        let (cst, t) = at(vv, b.2)?;
                        pts.push((vv, cst, t));
                    }
                }
            }
            let (bv, bc, bt) = pts
                .iter()
                .copied()
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .unwrap_or((v, f64::INFINITY, th));
            (v, th) = (bv, bt);
            let gain = (cost_hat - bc) / s2;
            if gain > best.dchi2 {
                best = Defocus {
                    z_um: z,
                    dchi2: gain,
                };
            }
            rises = if bc > last { rises + 1 } else { 0 };
            last = bc;
            // (no early stop within DEFOCUS_FULL_UM: a bead 0.54 µm off with a narrow pupil
            // read v 3.28 for 1.74, and the cost rose twice near the focus while v lagged)
            if rises >= 2 && dz >= DEFOCUS_FULL_UM {
                break;
            }
        }
    }
    Ok(best)
}
