//! Focused-beam Lorenz–Mie QPD response (paper Sec. 3.1, Fig. 2b and 3c).
//!
//! Method (docs/physics.md §9): angular-spectrum (plane-wave) representation of the focused
//! beam, exact vector Mie scattering of every plane wave by the sphere, and interference of the
//! scattered far field with the unscattered beam over the detection cone, per quadrant, with the
//! Rayleigh tier's detection nodes and channel signs ([`Detection`]).
//!
//! * **Beam.** E_inc(r) = Σ_j c_j ê_j e^{i k_j·r}: plane waves j on a Gauss–Legendre grid in
//!   θ_j ∈ [0, Θ_in] × a uniform (trapezoidal, exact for the periodic φ-integrand) grid in φ_j;
//!   Θ_in = Θ_obj = asin(min(NA, n)/n) (the objective aperture), or smaller where the Gaussian
//!   spectrum is below e^{−36}; c_j = Ã(θ_j) k² cosθ_j sinθ_j Δθ_j Δφ_j (dk_x dk_y),
//!   Ã = e^{−k² w0² sin²θ/4} (the plane-wave spectrum of a Gaussian waist w0; × 1/√cosθ with
//!   [`Apodization::Aplanatic`], the aplanatic objective, docs/physics.md §10), and
//!   ê_j = cosφ ê_θ − sinφ ê_φ (x-polarised pupil, Richards–Wolf), written without a
//!   singularity as ê = (1 − u²/(1+c), −uv/(1+c), −u), (u, v, c) = k̂.
//! * **Beam far field** (stationary phase of the angular spectrum, Mandel & Wolf §3.3):
//!   E_b(r r̂) = −2πi k cosθ Ã(θ) ê(r̂) e^{ikr}/r inside the aperture, 0 outside. Beam power
//!   P = ∫|E_b|² r² dΩ = 8π³ k² ∫₀^Θ_in cos²θ Ã² sinθ dθ (Gauss–Legendre, 256 nodes, exact to
//!   rounding).
//! * **Scattering** (Bohren & Huffman 1983, eq. 3.12 and 4.74, e^{−iωt}): for plane wave j and
//!   detection direction r̂_n, with ê_⊥ = r̂×k̂/|r̂×k̂|, ê_∥i = k̂×ê_⊥, ê_∥s = r̂×ê_⊥ (BH §3.2),
//!   E_s = Σ_j c_j e^{i k_j·x} e^{−ik r̂·x} (1/(−ik)) [S₂ (ê_j·ê_∥i) ê_∥s + S₁ (ê_j·ê_⊥) ê_⊥]
//!   · e^{ikr}/r for a sphere at displacement x (sphere − focus), S₁, S₂ from
//!   [`mie_s1s2_terms`] at every pair's exact cosΘ = k̂_j·r̂_n (no table, no interpolation).
//!   In the forward direction (|r̂×k̂| < 1e-12) the bracket is S(0)·ê_j.
//! * **Signals**: S_c = Σ_n s_c(n) wq_n [2 Re{E_s,n·E_b,n*} (+ |E_s,n|² if requested)] / P,
//!   wq_n = quadrature weight × sinθ of the detection node; normalised to the beam power,
//!   dimensionless, the same conventions as `optics::rayleigh` (Sx = right − left,
//!   Sy = top − bottom, displacement = particle − focus, µm; see docs/physics.md §1).
//!
//! **Cost.** The pair matrix M_nj = (2 wq_n/P) (bracket)·E_b,n* c_j/(−ik) does not depend on
//! the sphere position: it is built once per sphere (N·J Mie amplitude sums). Per position:
//! J + N complex exponentials and one N×J complex mat-vec (three for the gradient), i.e.
//! ≈ 8·N·J flops for (Sx, Sy, Sz), ≈ 24·N·J with the gradient; N = 4·n_theta·n_phi detection
//! nodes, J = 4·n_theta_in·n_phi_in incident plane waves. Measured numbers: docs/physics.md §9
//! and `cargo bench --features bench --bench mie_beam`.
//!
//! **Reach.** A discrete plane-wave sum represents the response only where both grids resolve
//! the phases k_j·x and k r̂_n·x ([`grid_reach_um`]): with the default grids ρ ≤ 1.5 µm
//! (≈ 1e-5 of the peak there; 1e-13 on the axis); further out it aliases (1e-2 of the peak at
//! 5 µm), so positions beyond the reach are refused with an error.
//! [`MieBeamSpec::for_reach`] and [`optics_for_reach`] give grids for a larger reach.

pub use super::beam::{filling_to_spectral_um, Apodization};
use super::beam::{theta_aperture, DipoleTier, OpticsArg, ValidOptics, DIPOLE_D_NM, DIPOLE_N};
use super::mie::{mie_s1s2_terms, Complex64 as C64, MieError};
use super::params::{check_above, check_range, Optics, OpticsError};
use super::quad::gauss_legendre;
use super::rayleigh::{Detection, DetectorModel};
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// (S, ∂S/∂x, ∂S/∂y) for the channels (Sx, Sy, Sz); derivatives in µm⁻¹.
pub type Grad3 = ([f64; 3], [f64; 3], [f64; 3]);

/// Which amplitude functions scatter each plane wave.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Amplitudes {
    /// Exact Lorenz–Mie S₁(Θ), S₂(Θ).
    Mie,
    /// Their dipole (Rayleigh) limit S₁ = −i x³ CM, S₂ = S₁ cosΘ (BH §5.2, e^{−iωt}),
    /// CM = (m² − 1)/(m² + 2): the same beam and detection with a point dipole of
    /// polarisability α = a³ CM, for separating beam-model effects from Mie effects.
    Dipole,
}

/// Accuracy knobs and options of the focused-beam Mie response.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct MieBeamSpec {
    /// Gauss–Legendre nodes in θ over the incident aperture [0, Θ_in].
    pub n_theta_in: usize,
    /// Uniform φ nodes per quadrant (4·n_phi_in over 2π, offset by half a step so the grid is
    /// symmetric under x → −x and y → −y).
    pub n_phi_in: usize,
    /// Detection model: the Rayleigh tier's nodes and channel signs (ideal or misaligned QPD).
    /// Its `polarization` flag is ignored: the Mie tier is always fully vectorial.
    pub detector: DetectorModel,
    /// Exact Mie amplitudes or their dipole limit.
    pub amplitudes: Amplitudes,
    /// Add the |E_s|² term (light scattered into the detection cone). The Rayleigh tier and the
    /// paper neglect it (main text eq. ReEE); it matters above ~300 nm (docs/physics.md §9).
    pub scattered_intensity: bool,
    /// Multipole count; `None` = `mie::default_terms` (Wiscombe's rule with a floor).
    pub n_terms: Option<usize>,
    /// Meaning of `Optics::w0_nm` for the angular spectrum ([`Waist`]).
    pub waist: Waist,
    /// Pupil apodisation of the objective ([`Apodization`]). `Aplanatic` is the vectorial focus
    /// of an aplanatic objective (Richards & Wolf 1959; Novotny & Hecht, *Principles of
    /// Nano-Optics*, 2nd ed., eq. 3.66); `None` is the beam this tier had before the one-beam work.
    pub apodization: Apodization,
}

impl Default for MieBeamSpec {
    /// Default grid: the knee of `accuracy::mie_knobs::knob_mie_grid` (docs/physics.md §9).
    fn default() -> Self {
        Self {
            n_theta_in: DEFAULT_N_THETA_IN,
            n_phi_in: DEFAULT_N_PHI_IN,
            detector: DetectorModel::default(),
            amplitudes: Amplitudes::Mie,
            scattered_intensity: false,
            n_terms: None,
            waist: Waist::Spectral,
            apodization: Apodization::None,
        }
    }
}

/// Default incident θ order: the knee of the accuracy sweep (`accuracy::mie_knobs::knob_mie_grid`, docs/accuracy.md),
/// i.e. the cheapest grid that is within 3e-5 of the peak *and* whose guaranteed reach
/// ([`grid_reach_um`]) covers the knob's region ρ ≤ 1.5 µm (docs/physics.md §9).
pub const DEFAULT_N_THETA_IN: usize = 12;
/// Default incident φ nodes per quadrant.
pub const DEFAULT_N_PHI_IN: usize = 6;
/// Largest accepted number of (detection node, plane wave) pairs: 8·10⁶ pairs is 128 MB for the
/// pair matrix (+384 MB with `scattered_intensity`).
pub const MAX_PAIRS: usize = 8_000_000;

impl MieBeamSpec {
    /// The default grids in the beam of `optics` ([`ResolvedBeam`](super::beam::ResolvedBeam)):
    /// in the vector beam the aplanatic focus of pupil filling `optics.pupil_filling`
    /// (docs/physics.md §10); in the paraxial beam §9's beam (spectral waist w0, no aplanatic
    /// factor).
    pub fn of_beam(optics: &ValidOptics) -> Self {
        Self::default().with_beam_of(optics)
    }

    /// This spec with the spectral waist and apodisation of the beam of `optics`
    /// ([`Self::of_beam`]).
    pub fn with_beam_of(self, optics: &ValidOptics) -> Self {
        let beam = optics.beam();
        Self {
            waist: Waist::SpectralUm(beam.spectral_waist_um()),
            apodization: beam.apodization(),
            ..self
        }
    }

    /// An incident grid that resolves the plane-wave phases out to a lateral distance
    /// `rho_um` from the focus at axial displacements up to `z_um` (the inverse of the
    /// incident-grid part of [`grid_reach_um`]): 4·n_phi_in ≥ kρ sinΘ + 12 and
    /// n_theta_in ≥ (kρ sinΘ + k|z|(1 − cosΘ)/2)/2.5 + 4. The detection grid must follow
    /// ([`optics_for_reach`]).
    pub fn for_reach(optics: &Optics, rho_um: f64, z_um: f64) -> Self {
        let k = optics.k_per_um();
        let th = theta_aperture(optics);
        let kr = k * rho_um.max(0.0) * th.sin();
        let kz = 0.5 * k * z_um.abs() * (1.0 - th.cos());
        Self {
            n_theta_in: (((kr + kz) / 2.5 + 4.0).ceil() as usize).clamp(8, 256),
            n_phi_in: (((kr + 12.0) / 4.0).ceil() as usize).clamp(4, 128),
            ..Self::default()
        }
    }
}

/// `optics` with the detection quadrature raised (never lowered) so that it resolves the
/// scattered far field out to a lateral distance `rho_um`: min(n_theta, 2 n_phi) ≥
/// 0.75 kρ sinΘ_det + 8 (the detection part of [`grid_reach_um`]).
pub fn optics_for_reach(optics: &Optics, rho_um: f64) -> Optics {
    let (nt, np) = reach_quadrature(optics, rho_um);
    Optics {
        n_theta: optics.n_theta.max(nt),
        n_phi: optics.n_phi.max(np),
        ..optics.clone()
    }
}

/// [`optics_for_reach`] for validated optics (the quadrature stays in the validated range).
pub fn valid_optics_for_reach(optics: &ValidOptics, rho_um: f64) -> ValidOptics {
    let (nt, np) = reach_quadrature(optics, rho_um);
    optics.with_min_quadrature(nt, np)
}

/// The detection quadrature (n_theta, n_phi) that resolves the scattered far field out to
/// `rho_um` ([`optics_for_reach`]): n_theta = ⌈0.75 kρ sinΘ_det + 8⌉ ≤ 256, n_phi = ⌈n_theta/2⌉.
fn reach_quadrature(optics: &Optics, rho_um: f64) -> (usize, usize) {
    let ks = optics.k_per_um() * optics.theta_max().sin();
    let nt = ((0.75 * ks * rho_um.max(0.0) + 8.0).ceil() as usize).min(256);
    (nt, nt.div_ceil(2))
}

/// Lateral reach (µm) of the plane-wave grids at axial displacement `z_um`: the largest
/// ρ = √(x² + y²) at which both the incident grid (`spec`) and the detection grid
/// (`optics.n_theta`, `optics.n_phi`) resolve the phases of the response to ≈ 1e-5 of its
/// peak. Calibrated against (48, 24)/(40, 20) reference grids for 110 and 500 nm beads
/// (docs/physics.md §9):
///   incident:  ρ ≤ min(4 n_phi_in − 12, 2.5 (n_theta_in − 4) − k|z|(1 − cosΘ)/2) / (k sinΘ),
///   detection: ρ ≤ (min(n_theta, 2 n_phi) − 8) / (0.75 k sinΘ_det).
/// Beyond it a discrete plane-wave sum aliases (errors of 1e-2 of the peak at 5 µm with the
/// default grids), so [`MieBeam::response`] refuses such positions.
pub fn grid_reach_um(optics: &Optics, spec: &MieBeamSpec, z_um: f64) -> f64 {
    let k = optics.k_per_um();
    let th = theta_aperture(optics);
    let ks_in = k * th.sin();
    let ks_det = k * optics.theta_max().sin();
    let r_phi = (4.0 * spec.n_phi_in as f64 - 12.0) / ks_in;
    let r_th =
        (2.5 * (spec.n_theta_in as f64 - 4.0) - 0.5 * k * z_um.abs() * (1.0 - th.cos())) / ks_in;
    let r_det = ((optics.n_theta.min(2 * optics.n_phi)) as f64 - 8.0) / (0.75 * ks_det);
    r_phi.min(r_th).min(r_det).max(0.0)
}

/// Polarisation of the x-polarised pupil at direction (u, v, c): cosφ ê_θ − sinφ ê_φ.
#[inline]
fn pupil_pol(u: f64, v: f64, c: f64) -> [f64; 3] {
    let q = 1.0 / (1.0 + c);
    [1.0 - u * u * q, -u * v * q, -u]
}

#[inline]
fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

#[inline]
fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Vector far-field amplitude [S₂(ê·ê_∥i) ê_∥s + S₁(ê·ê_⊥) ê_⊥] for incident direction `kh`,
/// incident polarisation `e` (⊥ kh), scattering direction `rh` (BH eq. 3.12, bases of BH §3.2).
pub fn scattering_vector(kh: [f64; 3], e: [f64; 3], rh: [f64; 3], s1: C64, s2: C64) -> [C64; 3] {
    let cr = cross(rh, kh);
    let nrm = dot(cr, cr).sqrt();
    if nrm < 1e-12 {
        // forward (S₁ = S₂ = S(0)); project in case |Θ| is tiny but not zero
        let s = 0.5 * (s1 + s2);
        let er = dot(e, rh);
        return [
            s * (e[0] - er * rh[0]),
            s * (e[1] - er * rh[1]),
            s * (e[2] - er * rh[2]),
        ];
    }
    let ep = [cr[0] / nrm, cr[1] / nrm, cr[2] / nrm];
    let e_par_in = cross(kh, ep);
    let e_par_sc = cross(rh, ep);
    let a = s2 * dot(e, e_par_in);
    let b = s1 * dot(e, ep);
    [
        a * e_par_sc[0] + b * ep[0],
        a * e_par_sc[1] + b * ep[1],
        a * e_par_sc[2] + b * ep[2],
    ]
}

/// What `Optics::w0_nm` means for the angular-spectrum beam.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Default)]
pub enum Waist {
    /// w0 is the parameter of the Gaussian plane-wave spectrum e^{−k² w0² sin²θ/4} (the lead's
    /// design; equals the focal 1/e² radius only for a paraxial, untruncated beam). For the
    /// paper's w0 = 400 nm and NA 1.2 the focus is then 536 nm (along the polarisation) ×
    /// 452 nm wide (docs/physics.md §9).
    #[default]
    Spectral,
    /// w0 is the 1/e² radius of the focal intensity (the paper's definition, Sec. 3.1: "the
    /// radius at which the light intensity in the focal plane decreases by 1/e²"), averaged
    /// over the x and y directions: the spectral parameter is solved for by
    /// [`spectral_waist_nm`]. NA 1.2 at 1064 nm cannot focus tighter than a mean 412 nm
    /// (uniformly filled aperture), so the paper's 400 nm gives an error naming that minimum.
    Focal,
    /// An explicit spectral waist in nm (ignores `Optics::w0_nm`); 0 = uniformly filled
    /// (overfilled) aperture, the tightest focus the objective can make.
    SpectralNm(f64),
    /// Gaussian pupil filling factor f0 ([`filling_to_spectral_um`], Novotny & Hecht eq. 3.52);
    /// f64::INFINITY = uniformly filled. Ignores `Optics::w0_nm`.
    Filling(f64),
    /// An explicit spectral waist in µm: the resolved beam's ([`MieBeamSpec::of_beam`]).
    SpectralUm(f64),
}

/// The focused beam as a discrete angular spectrum (module docs): plane waves on a
/// Gauss–Legendre × uniform grid over the aperture, with the Gaussian spectrum of parameter
/// `w_spec` (µm).
#[derive(Debug, Clone)]
pub struct AngularSpectrum {
    /// wavenumber in the medium, µm⁻¹
    pub k: f64,
    /// spectral waist parameter, µm
    pub w_spec: f64,
    /// upper polar angle of the grid (aperture or numerical cut), rad
    pub theta_in: f64,
    /// wave vectors k_j (µm⁻¹), unit directions, polarisations ê_j, weights c_j = Ã dk_x dk_y
    pub kin: Vec<[f64; 3]>,
    pub khat: Vec<[f64; 3]>,
    pub ein: Vec<[f64; 3]>,
    pub cw: Vec<f64>,
    /// pupil apodisation (aplanatic factor or none)
    pub apodization: Apodization,
    /// beam power ∫|E_b|² r² dΩ (µm⁻², the units of [`AngularSpectrum::field`] squared × µm²)
    pub power: f64,
}

impl AngularSpectrum {
    /// Build the plane-wave grid for `optics` (k, aperture NA) with spectral waist `w_spec_um`.
    pub fn new(
        optics: &Optics,
        w_spec_um: f64,
        n_theta_in: usize,
        n_phi_in: usize,
    ) -> Result<Self, OpticsError> {
        Self::with_apodization(optics, w_spec_um, n_theta_in, n_phi_in, Apodization::None)
    }

    /// As [`AngularSpectrum::new`] with a pupil apodisation: amplitude per dk_x dk_y
    /// Ã(θ) g(θ) ([`Apodization::factor`]); c_j = Ã g k² cosθ sinθ Δθ Δφ.
    pub fn with_apodization(
        optics: &Optics,
        w_spec_um: f64,
        n_theta_in: usize,
        n_phi_in: usize,
        apodization: Apodization,
    ) -> Result<Self, OpticsError> {
        check_range("w_spec_um", w_spec_um, 0.0, 1000.0)?;
        check_range("n_theta_in", n_theta_in as f64, 2.0, 512.0)?;
        check_range("n_phi_in", n_phi_in as f64, 1.0, 512.0)?;
        let k = optics.k_per_um();
        let th_obj = theta_aperture(optics);
        // numerical cut where the spectrum is below e^{-36} (never beyond the aperture)
        let th_num = if k * w_spec_um > 12.0 {
            (12.0 / (k * w_spec_um)).asin()
        } else {
            PI / 2.0
        };
        let theta_in = th_obj.min(th_num);
        let mut out = Self {
            k,
            w_spec: w_spec_um,
            theta_in,
            kin: Vec::new(),
            khat: Vec::new(),
            ein: Vec::new(),
            cw: Vec::new(),
            apodization,
            power: 0.0,
        };
        // beam power: 8π³k² ∫ cos²θ (Ã g)² sinθ dθ
        let (tp, wp) = gauss_legendre(256, 0.0, theta_in);
        out.power = 8.0
            * PI.powi(3)
            * k
            * k
            * tp.iter()
                .zip(&wp)
                .map(|(&t, &w)| {
                    let (s, c) = t.sin_cos();
                    w * c * c * out.amplitude(s, c).powi(2) * s
                })
                .sum::<f64>();
        let (th, wth) = gauss_legendre(n_theta_in, 0.0, theta_in);
        let nphi = 4 * n_phi_in;
        let dphi = 2.0 * PI / nphi as f64;
        for (&t, &wt) in th.iter().zip(&wth) {
            let (st, ct) = t.sin_cos();
            let c = out.amplitude(st, ct) * k * k * ct * st * wt * dphi;
            for i in 0..nphi {
                let (sp, cp) = ((i as f64 + 0.5) * dphi).sin_cos();
                let kh = [st * cp, st * sp, ct];
                out.khat.push(kh);
                out.kin.push([k * kh[0], k * kh[1], k * kh[2]]);
                out.ein.push(pupil_pol(kh[0], kh[1], kh[2]));
                out.cw.push(c);
            }
        }
        Ok(out)
    }

    /// Gaussian spectrum Ã at sinθ.
    #[inline]
    pub fn spectrum(&self, sin_theta: f64) -> f64 {
        (-(self.k * self.w_spec * sin_theta).powi(2) / 4.0).exp()
    }

    /// Plane-wave amplitude per dk_x dk_y at (sinθ, cosθ): Ã(θ) times the apodisation factor.
    #[inline]
    pub fn amplitude(&self, sin_theta: f64, cos_theta: f64) -> f64 {
        self.spectrum(sin_theta) * self.apodization.factor(cos_theta)
    }

    /// Focal field at (x, y, z) µm; |E|²/power is the intensity per unit power (µm⁻²).
    pub fn field(&self, x: f64, y: f64, z: f64) -> [C64; 3] {
        let mut e = [C64::new(0.0, 0.0); 3];
        for ((kj, ej), &c) in self.kin.iter().zip(&self.ein).zip(&self.cw) {
            let (s, co) = (kj[0] * x + kj[1] * y + kj[2] * z).sin_cos();
            let p = C64::new(co, s) * c;
            for a in 0..3 {
                e[a] += p * ej[a];
            }
        }
        e
    }

    /// Intensity per unit power |E|²/P at (x, y, z) µm, µm⁻².
    pub fn intensity(&self, x: f64, y: f64, z: f64) -> f64 {
        let e = self.field(x, y, z);
        (e[0].norm_sqr() + e[1].norm_sqr() + e[2].norm_sqr()) / self.power
    }

    /// 1/e² radii of the focal-plane intensity along x (the polarisation) and y, µm (first
    /// crossing of I(0)·e^{−2} going outward, by bisection on a 5 nm bracket scan).
    pub fn focal_radii(&self) -> (f64, f64) {
        let i0 = self.intensity(0.0, 0.0, 0.0);
        let target = i0 * (-2.0f64).exp();
        let find = |f: &dyn Fn(f64) -> f64| {
            let mut a = 0.0;
            let mut b = 0.005;
            while f(b) > target && b < 20.0 {
                a = b;
                b += 0.005;
            }
            for _ in 0..50 {
                let m = 0.5 * (a + b);
                if f(m) > target {
                    a = m
                } else {
                    b = m
                }
            }
            0.5 * (a + b)
        };
        (
            find(&|x| self.intensity(x, 0.0, 0.0)),
            find(&|y| self.intensity(0.0, y, 0.0)),
        )
    }
}

/// The spectral waist (nm) for which the angular-spectrum focus of `optics` has a 1/e²
/// intensity radius, averaged over x and y, equal to `optics.w0_nm` ([`Waist::Focal`]).
/// Bisection on the spectral waist (the focal radius grows monotonically with it), 40 steps;
/// focal field from a (32, 16) incident grid (converged to < 1e-9 within 1.5 µm).
/// Errors if w0 is below the tightest focus the aperture allows (uniform filling), naming
/// `w0_nm`, its value and that minimum.
pub fn spectral_waist_nm(optics: &impl OpticsArg) -> Result<f64, OpticsError> {
    spectral_waist_nm_with(optics, Apodization::None)
}

/// [`spectral_waist_nm`] for a beam with pupil apodisation `apodization`.
pub fn spectral_waist_nm_with(
    optics: &impl OpticsArg,
    apodization: Apodization,
) -> Result<f64, OpticsError> {
    let optics = optics.valid()?;
    let optics: &Optics = &optics;
    let mean_r = |ws: f64| -> Result<f64, OpticsError> {
        let b = AngularSpectrum::with_apodization(optics, ws, 32, 16, apodization)?;
        let (rx, ry) = b.focal_radii();
        Ok(0.5 * (rx + ry))
    };
    let target = optics.w0_um();
    let r_min = mean_r(0.0)?;
    if target <= r_min {
        return Err(OpticsError::OutOfRange {
            name: "w0_nm",
            value: optics.w0_nm,
            allowed: format!(
                "w0_nm > {:.1} nm: the tightest focus of NA {} at {} nm (uniformly filled aperture) with Waist::Focal",
                1e3 * r_min,
                optics.na,
                optics.wavelength_nm
            ),
        });
    }
    let (mut a, mut b) = (0.0, target.max(0.05));
    while mean_r(b)? < target {
        a = b;
        b *= 2.0;
        if b > 1000.0 {
            break;
        }
    }
    for _ in 0..40 {
        let m = 0.5 * (a + b);
        if mean_r(m)? < target {
            a = m
        } else {
            b = m
        }
    }
    Ok(1e3 * 0.5 * (a + b))
}

/// A sphere in the focused beam, with everything that does not depend on its position
/// precomputed (the pair matrix). See the module docs for the model and its cost.
#[derive(Debug, Clone)]
pub struct MieBeam {
    k: f64,
    /// the incident beam
    beam: AngularSpectrum,
    /// detection directions r̂_n and channel signs
    rdet: Vec<[f64; 3]>,
    sdet: Vec<[f64; 3]>,
    /// pair matrix, N×J row-major, split in real and imaginary parts
    m_re: Vec<f64>,
    m_im: Vec<f64>,
    /// scattered-field pair vectors × √(wq_n/P) (only with `scattered_intensity`), N×J×3
    v: Option<Vec<[C64; 3]>>,
    /// The point dipole's rank-3 factorisation of the pair matrix (`Amplitudes::Dipole` without
    /// the |E_s|² term; the pair matrix is then left empty): M[n][j] = Σ_c U[n][c]·W[c][j] with
    /// W[c][j] = ê_j[c]·w_j the incident plane waves' field components, so the response at r is
    /// Re Σ_n s_n e^{−ik r̂_n·r} U[n]·E(r) with E(r) = Σ_j W[·][j] e^{ik_j·r}: J + N operations
    /// per position instead of J·N.
    dipole: Option<DipoleFactors>,
    power: f64,
    theta_in: f64,
    x_size: f64,
    m_rel: C64,
    d_nm: f64,
    spec: MieBeamSpec,
    optics: ValidOptics,
}

/// See [`MieBeam::dipole`]: U per detection node, W per field component (row-major c, j).
#[derive(Debug, Clone)]
struct DipoleFactors {
    u: Vec<[C64; 3]>,
    w: [Vec<f64>; 3],
}

fn mie_err(e: MieError) -> OpticsError {
    OpticsError::Invalid(e.to_string())
}

impl MieBeam {
    /// Build the response of a sphere of diameter `d_nm` (nm, 0 < d ≤ 20000) and complex index
    /// `n_particle` (Bohren–Huffman convention: Im ≥ 0 absorbs; 0 < Re ≤ 5) in the focused beam
    /// of `optics` (w0, λ, n_medium, objective NA = `optics.na`; detection cone and quadrature
    /// from `optics.n_theta`, `optics.n_phi`, `optics.qpd_na` and `spec.detector`).
    ///
    /// Errors name the argument, its value and the allowed range.
    pub fn new(
        optics: &impl OpticsArg,
        d_nm: f64,
        n_particle: C64,
        spec: MieBeamSpec,
    ) -> Result<Self, OpticsError> {
        Self::build(&*optics.valid()?, d_nm, n_particle, spec, true)
    }

    /// The sphere and the incident grid `build` accepts: errors name the argument and range.
    fn check_inputs(d_nm: f64, n_particle: C64, spec: &MieBeamSpec) -> Result<(), OpticsError> {
        check_above("d_nm", d_nm, 0.0)?;
        check_range("d_nm", d_nm, 0.0, 20000.0)?;
        check_range("n_particle (real part)", n_particle.re, 1e-3, 5.0)?;
        check_range("n_particle (imaginary part)", n_particle.im, 0.0, 10.0)?;
        check_range("n_theta_in", spec.n_theta_in as f64, 2.0, 512.0)?;
        check_range("n_phi_in", spec.n_phi_in as f64, 1.0, 512.0)?;
        if let Some(nt) = spec.n_terms {
            check_range("n_terms", nt as f64, 1.0, 10000.0)?;
        }
        Ok(())
    }

    /// [`Self::new`]; `factorise` = false keeps the pair matrix for the point dipole too (the
    /// unit test that checks the factorisation against it).
    fn build(
        optics: &ValidOptics,
        d_nm: f64,
        n_particle: C64,
        spec: MieBeamSpec,
        factorise: bool,
    ) -> Result<Self, OpticsError> {
        Self::check_inputs(d_nm, n_particle, &spec)?;
        let det = Detection::new(optics, &spec.detector)?;
        let n_det = det.nodes.len();
        let n_inc = 4 * spec.n_theta_in * spec.n_phi_in;
        if n_det * n_inc > MAX_PAIRS {
            return Err(OpticsError::Invalid(format!(
                "grid too large: {n_det} detection nodes (4·n_theta·n_phi, n_theta = {}, n_phi = {}) × {n_inc} plane waves (4·n_theta_in·n_phi_in, n_theta_in = {}, n_phi_in = {}) = {} pairs; allowed ≤ {MAX_PAIRS}",
                optics.n_theta,
                optics.n_phi,
                spec.n_theta_in,
                spec.n_phi_in,
                n_det * n_inc
            )));
        }
        let k = optics.k_per_um();
        let w_spec = match spec.waist {
            Waist::Spectral => optics.w0_um(),
            Waist::Focal => spectral_waist_nm_with(optics, spec.apodization)? * 1e-3,
            Waist::SpectralNm(w) => check_range("waist (spectral, nm)", w, 0.0, 1e6)? * 1e-3,
            Waist::Filling(f0) => filling_to_spectral_um(optics, f0)?,
            Waist::SpectralUm(w) => check_range("waist (spectral, µm)", w, 0.0, 1e3)?,
        };
        let beam = AngularSpectrum::with_apodization(
            optics,
            w_spec,
            spec.n_theta_in,
            spec.n_phi_in,
            spec.apodization,
        )?;
        let theta_in = beam.theta_in;
        let power = beam.power;
        let amplitude = |st: f64, ct: f64| beam.amplitude(st, ct);
        let (khat, ein, cw) = (&beam.khat, &beam.ein, &beam.cw);

        // scatterer
        let m_rel = n_particle / optics.n_medium;
        let x_size = PI * d_nm * optics.n_medium / optics.wavelength_nm;
        let cm = (m_rel * m_rel - 1.0) / (m_rel * m_rel + 2.0);
        let s_dip = C64::new(0.0, -x_size.powi(3)) * cm;

        // the point dipole factorises (see `MieBeam::dipole`); no pair matrix then
        let factorised =
            factorise && spec.amplitudes == Amplitudes::Dipole && !spec.scattered_intensity;
        let pairs = if factorised { 0 } else { n_det * n_inc };
        let mut dip_u = Vec::with_capacity(if factorised { n_det } else { 0 });
        // pair matrix
        let mut m_re = vec![0.0; pairs];
        let mut m_im = vec![0.0; pairs];
        let mut vmat = if spec.scattered_intensity {
            Some(vec![[C64::new(0.0, 0.0); 3]; n_det * n_inc])
        } else {
            None
        };
        let inv_mik = C64::new(0.0, 1.0 / k); // 1/(−ik)
        let mut rdet = Vec::with_capacity(n_det);
        let mut sdet = Vec::with_capacity(n_det);
        let mut cosv = vec![0.0; n_inc];
        for (n, node) in det.nodes.iter().enumerate() {
            let rh = [node.u, node.v, node.c];
            rdet.push(rh);
            sdet.push(node.s);
            let sn = node.u.hypot(node.v);
            // E_b,n = −2πi k c Ã g ê_b (zero outside the incident aperture)
            let eb_amp = if sn.asin() <= theta_in + 1e-12 {
                2.0 * PI * k * node.c * amplitude(sn, node.c)
            } else {
                0.0
            };
            let eb = pupil_pol(node.u, node.v, node.c);
            // E_b* = +2πi k c Ã ê_b  →  bracket·E_b* = (bracket·ê_b)·(i eb_amp)
            let pref = 2.0 * node.wq / power;
            if factorised {
                // dipole bracket: s_dip (ê_j − r̂ (r̂·ê_j)), so bracket·ê_b = Σ_c ê_j[c] q[c]
                // with q = ê_b − r̂ (r̂·ê_b); the rest of the pair's factor is the node's
                let zero_contrast = m_rel == C64::new(1.0, 0.0);
                let g = if zero_contrast {
                    C64::new(0.0, 0.0)
                } else {
                    s_dip * inv_mik * C64::new(0.0, eb_amp * pref)
                };
                let rb = dot(rh, eb);
                dip_u.push([0, 1, 2].map(|c| g * (eb[c] - rh[c] * rb)));
                continue;
            }
            for (j, kh) in khat.iter().enumerate() {
                cosv[j] = dot(*kh, rh).clamp(-1.0, 1.0);
            }
            let s12: Vec<(C64, C64)> = match spec.amplitudes {
                // zero contrast scatters nothing: exact zeros (the recurrences leave ~1e-17)
                _ if m_rel == C64::new(1.0, 0.0) => {
                    vec![(C64::new(0.0, 0.0), C64::new(0.0, 0.0)); n_inc]
                }
                Amplitudes::Mie => {
                    mie_s1s2_terms(x_size, m_rel, &cosv, spec.n_terms).map_err(mie_err)?
                }
                Amplitudes::Dipole => cosv.iter().map(|&c| (s_dip, s_dip * c)).collect(),
            };
            let vscale = (node.wq / power).sqrt();
            for j in 0..n_inc {
                let (s1, s2) = s12[j];
                let sv = scattering_vector(khat[j], ein[j], rh, s1, s2);
                let f = inv_mik * cw[j];
                let proj = (sv[0] * eb[0] + sv[1] * eb[1] + sv[2] * eb[2])
                    * f
                    * C64::new(0.0, eb_amp * pref);
                m_re[n * n_inc + j] = proj.re;
                m_im[n * n_inc + j] = proj.im;
                if let Some(v) = vmat.as_mut() {
                    let g = f * vscale;
                    v[n * n_inc + j] = [sv[0] * g, sv[1] * g, sv[2] * g];
                }
            }
        }
        let dipole = factorised.then(|| DipoleFactors {
            u: dip_u,
            w: [0, 1, 2].map(|c| ein.iter().zip(cw).map(|(e, w)| e[c] * w).collect()),
        });
        let out = Self {
            k,
            beam,
            rdet,
            sdet,
            m_re,
            m_im,
            v: vmat,
            dipole,
            power,
            theta_in,
            x_size,
            m_rel,
            d_nm,
            spec,
            optics: optics.clone(),
        };
        Ok(out)
    }

    /// Size parameter x = π d n_medium / λ.
    pub fn size_parameter(&self) -> f64 {
        self.x_size
    }
    /// Relative index m = n_particle / n_medium.
    pub fn relative_index(&self) -> C64 {
        self.m_rel
    }
    /// Diameter, nm.
    pub fn d_nm(&self) -> f64 {
        self.d_nm
    }
    /// The spec the response was built with.
    pub fn spec(&self) -> &MieBeamSpec {
        &self.spec
    }
    /// Upper polar angle of the incident plane-wave grid (rad): the objective aperture, or the
    /// numerical cut where the Gaussian spectrum is below e^{−36}.
    pub fn theta_in(&self) -> f64 {
        self.theta_in
    }
    /// Focal field E_inc at displacement (x, y, z) µm, in units where |E|²/[`Self::beam_power`] is
    /// the intensity per unit beam power in µm⁻² (a paraxial Gaussian has 2/(π w0²) at its waist).
    pub fn focal_field(&self, x: f64, y: f64, z: f64) -> [C64; 3] {
        self.beam.field(x, y, z)
    }

    /// The incident beam (plane-wave grid, spectral waist, power).
    pub fn beam(&self) -> &AngularSpectrum {
        &self.beam
    }

    /// Beam power P = ∫|E_b|² r² dΩ in the units of [`Self::focal_field`] (µm⁻²).
    pub fn beam_power(&self) -> f64 {
        self.power
    }

    /// True when the response has the parities of a mirror-symmetric instrument (Sx odd in x
    /// and even in y, Sy even in x and odd in y, Sz even in both): an ideal QPD (its detection
    /// rule made of mirror quartets, as [`Detection::mirror_symmetric`]); the beam, polarised
    /// along x with a radial apodization and a φ rule offset by half a step, always is.
    pub fn mirror_symmetric(&self) -> bool {
        self.spec.detector.misalignment.is_none()
    }

    /// [`Self::response`] at the nodes (xs[i], ys[j]) of a grid in the plane z (row-major, j
    /// slow), zero where `keep(x, y)` is false. The phases are separable on a grid,
    /// e^{ik·r} = e^{ik_x x}·e^{i(k_y y + k_z z)}, so they come from tables built once per column
    /// and once per row — products instead of N + J `sin_cos` per node (the plane's cost) — and
    /// agree with [`Self::response`]'s to rounding (≲ 1e-15 relative; unit test). Rows in
    /// parallel.
    pub fn responses_on_grid(
        &self,
        xs: &[f64],
        ys: &[f64],
        z: f64,
        keep: &(dyn Fn(f64, f64) -> bool + Sync),
    ) -> Result<Vec<[f64; 3]>, OpticsError> {
        use rayon::prelude::*;
        // the checks of `response`: every coordinate in range, and the farthest node kept
        // within the grids' reach
        for &x in xs {
            check_range("x", x, -1e4, 1e4)?;
        }
        for &y in ys {
            check_range("y", y, -1e4, 1e4)?;
        }
        let mut far: Option<(f64, f64, f64)> = None;
        for &x in xs {
            for &y in ys {
                let r2 = x * x + y * y;
                if far.is_none_or(|f| r2 > f.2) && keep(x, y) {
                    far = Some((x, y, r2));
                }
            }
        }
        match far {
            Some((x, y, _)) => self.check_pos(x, y, z)?,
            None => {
                check_range("z", z, -1e4, 1e4)?;
            }
        }
        let k = self.k;
        let cis = |a: f64| {
            let (s, c) = a.sin_cos();
            C64::new(c, s)
        };
        // per column: incident e^{i k_jx x} (J × nx) and detection e^{−ik u_n x} (N × nx)
        let inc_x: Vec<Vec<C64>> = xs
            .par_iter()
            .map(|&x| self.beam.kin.iter().map(|kj| cis(kj[0] * x)).collect())
            .collect();
        let det_x: Vec<Vec<C64>> = xs
            .par_iter()
            .map(|&x| self.rdet.iter().map(|rh| cis(-k * rh[0] * x)).collect())
            .collect();
        let rows: Vec<Vec<[f64; 3]>> = ys
            .par_iter()
            .map(|&y| {
                let inc_yz: Vec<C64> = self
                    .beam
                    .kin
                    .iter()
                    .map(|kj| cis(kj[1] * y + kj[2] * z))
                    .collect();
                let det_yz: Vec<C64> = self
                    .rdet
                    .iter()
                    .map(|rh| cis(-k * (rh[1] * y + rh[2] * z)))
                    .collect();
                let (mut ar, mut ai, mut det) = (Vec::new(), Vec::new(), Vec::new());
                xs.iter()
                    .enumerate()
                    .map(|(i, &x)| {
                        if !keep(x, y) {
                            return [0.0; 3];
                        }
                        ar.clear();
                        ai.clear();
                        for (a, b) in inc_x[i].iter().zip(&inc_yz) {
                            let p = a * b;
                            ar.push(p.re);
                            ai.push(p.im);
                        }
                        det.clear();
                        det.extend(det_x[i].iter().zip(&det_yz).map(|(a, b)| a * b));
                        self.eval_phased(&ar, &ai, &det, false).0
                    })
                    .collect()
            })
            .collect();
        Ok(rows.into_iter().flatten().collect())
    }

    /// (Sx, Sy, Sz) at displacement (x, y, z) µm (sphere − focus), normalised to the beam power
    /// (dimensionless). Errors if a coordinate is non-finite or beyond ±1e4 µm.
    pub fn response(&self, x: f64, y: f64, z: f64) -> Result<[f64; 3], OpticsError> {
        self.check_pos(x, y, z)?;
        Ok(self.eval(x, y, z, false).0)
    }

    /// (S, ∂S/∂x, ∂S/∂y) for the three channels at (x, y, z) µm; derivatives analytic (µm⁻¹).
    pub fn response_grad(&self, x: f64, y: f64, z: f64) -> Result<Grad3, OpticsError> {
        self.check_pos(x, y, z)?;
        Ok(self.eval(x, y, z, true))
    }

    /// (Sx, Sy, Sz) at (x, y, z) µm without the range and reach checks of [`Self::response`]:
    /// for convergence studies (the accuracy report's `mie_grid` knob) that measure how wrong a
    /// grid is beyond its reach. Not for measurements.
    pub fn response_unchecked(&self, x: f64, y: f64, z: f64) -> [f64; 3] {
        self.eval(x, y, z, false).0
    }

    /// ∂Sx/∂x at x = y = 0 and axial displacement z µm (analytic derivative), µm⁻¹.
    pub fn sensitivity_x(&self, z: f64) -> Result<f64, OpticsError> {
        self.check_pos(0.0, 0.0, z)?;
        Ok(self.eval(0.0, 0.0, z, true).1[0])
    }

    /// Maximum of ∂Sx/∂x over the axial position (the paper optimises the height before every
    /// scan, suppl. S5) and the z where it occurs: a 0.05 µm scan of z ∈ [−1, 1] µm, then golden
    /// section to 1e-7 µm (the same search as `finite_size::max_sensitivity_unit`).
    pub fn max_sensitivity_x(&self) -> (f64, f64) {
        self.extreme_sensitivity_x(1.0)
    }

    /// [`Self::max_sensitivity_x`] for a sphere whose polarisability has the sign `sign`: for
    /// `sign` < 0 (index below the medium's) the central lobe's slope is negative, and its
    /// extreme is the minimum of ∂Sx/∂x over z (the maximum would be an overshoot lobe) — the
    /// same signed value the point dipole gives, α × the unit response's maximum.
    pub fn extreme_sensitivity_x(&self, sign: f64) -> (f64, f64) {
        let s = if sign < 0.0 { -1.0 } else { 1.0 };
        let (v, z) = super::finite_size::best_focus(|z| s * self.eval(0.0, 0.0, z, true).1[0]);
        (s * v, z)
    }

    /// Lateral reach (µm) of this response's grids at axial displacement z ([`grid_reach_um`]).
    pub fn reach_um(&self, z: f64) -> f64 {
        grid_reach_um(&self.optics, &self.spec, z)
    }

    /// Positions must be finite, |x|, |y|, |z| ≤ 1e4 µm, and within the grids' reach.
    fn check_pos(&self, x: f64, y: f64, z: f64) -> Result<(), OpticsError> {
        check_range("x", x, -1e4, 1e4)?;
        check_range("y", y, -1e4, 1e4)?;
        check_range("z", z, -1e4, 1e4)?;
        let rho = x.hypot(y);
        let reach = self.reach_um(z);
        if rho > reach {
            return Err(OpticsError::OutOfRange {
                name: "ρ = √(x² + y²) (µm)",
                value: rho,
                allowed: format!(
                    "ρ ≤ {reach:.3} µm at z = {z} µm, the reach of the plane-wave grids (incident n_theta_in = {}, n_phi_in = {}; detection n_theta = {}, n_phi = {}); build with MieBeamSpec::for_reach and mie_beam::optics_for_reach for a larger reach",
                    self.spec.n_theta_in, self.spec.n_phi_in, self.optics.n_theta, self.optics.n_phi
                ),
            });
        }
        Ok(())
    }

    fn eval(&self, x: f64, y: f64, z: f64, grad: bool) -> Grad3 {
        let nj = self.beam.kin.len();
        let mut ar = Vec::with_capacity(nj);
        let mut ai = Vec::with_capacity(nj);
        for kj in &self.beam.kin {
            let (s, c) = (kj[0] * x + kj[1] * y + kj[2] * z).sin_cos();
            ar.push(c);
            ai.push(s);
        }
        let k = self.k;
        let det: Vec<C64> = self
            .rdet
            .iter()
            .map(|rh| {
                let (ps, pc) = (-k * (rh[0] * x + rh[1] * y + rh[2] * z)).sin_cos();
                C64::new(pc, ps)
            })
            .collect();
        self.eval_phased(&ar, &ai, &det, grad)
    }

    /// [`Self::eval`] from the phases at the position: the incident plane waves'
    /// e^{ik_j·r} = ar + i·ai and the detection directions' e^{−ik r̂_n·r} = `det`.
    fn eval_phased(&self, ar: &[f64], ai: &[f64], det: &[C64], grad: bool) -> Grad3 {
        if let Some(d) = &self.dipole {
            return self.eval_dipole(d, ar, ai, det, grad);
        }
        let nj = self.beam.kin.len();
        let (mut bxr, mut bxi, mut byr, mut byi) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        if grad {
            for (j, kj) in self.beam.kin.iter().enumerate() {
                bxr.push(ar[j] * kj[0]);
                bxi.push(ai[j] * kj[0]);
                byr.push(ar[j] * kj[1]);
                byi.push(ai[j] * kj[1]);
            }
        }
        let k = self.k;
        let mut s = [0.0; 3];
        let mut dx = [0.0; 3];
        let mut dy = [0.0; 3];
        for (n, (rh, sg)) in self.rdet.iter().zip(&self.sdet).enumerate() {
            let row = n * nj..(n + 1) * nj;
            let (mr, mi) = (&self.m_re[row.clone()], &self.m_im[row.clone()]);
            let ph = det[n];
            let (val, gx, gy);
            if grad {
                // ∂/∂x: i (Σ M a k_jx − k u_n Σ M a)
                let [w, wx, wy] = cdot3(mr, mi, [(ar, ai), (&bxr, &bxi), (&byr, &byi)]);
                let i = C64::new(0.0, 1.0);
                val = (ph * w).re;
                gx = (ph * i * (wx - w * (k * rh[0]))).re;
                gy = (ph * i * (wy - w * (k * rh[1]))).re;
            } else {
                val = (ph * cdot(mr, mi, ar, ai)).re;
                gx = 0.0;
                gy = 0.0;
            }
            let (mut q, mut qx, mut qy) = (0.0, 0.0, 0.0);
            if let Some(v) = &self.v {
                let vrow = &v[row];
                let mut e = [C64::new(0.0, 0.0); 3];
                let mut ex = [C64::new(0.0, 0.0); 3];
                let mut ey = [C64::new(0.0, 0.0); 3];
                for j in 0..nj {
                    let a = C64::new(ar[j], ai[j]);
                    for c in 0..3 {
                        let t = vrow[j][c] * a;
                        e[c] += t;
                        if grad {
                            ex[c] += t * self.beam.kin[j][0];
                            ey[c] += t * self.beam.kin[j][1];
                        }
                    }
                }
                for c in 0..3 {
                    q += e[c].norm_sqr();
                    if grad {
                        // ∂|E|² = 2 Re{E* · i Σ V a k_j}
                        qx += 2.0 * (e[c].conj() * ex[c] * C64::new(0.0, 1.0)).re;
                        qy += 2.0 * (e[c].conj() * ey[c] * C64::new(0.0, 1.0)).re;
                    }
                }
            }
            for c in 0..3 {
                s[c] += sg[c] * (val + q);
                dx[c] += sg[c] * (gx + qx);
                dy[c] += sg[c] * (gy + qy);
            }
        }
        (s, dx, dy)
    }
}

impl MieBeam {
    /// [`Self::eval`] for the factorised point dipole: the incident field E(r) and, with
    /// `grad`, its x and y derivatives i Σ_j W_j k_jx,y e^{ik_j·r}, then one 3-vector product per
    /// detection node. Same signal and derivative as the pair-matrix path (unit test).
    fn eval_dipole(
        &self,
        d: &DipoleFactors,
        ar: &[f64],
        ai: &[f64],
        det: &[C64],
        grad: bool,
    ) -> Grad3 {
        let zero = C64::new(0.0, 0.0);
        let (mut e, mut ex, mut ey) = ([zero; 3], [zero; 3], [zero; 3]);
        for (j, kj) in self.beam.kin.iter().enumerate() {
            let (sn, cs) = (ai[j], ar[j]);
            for c in 0..3 {
                let t = C64::new(d.w[c][j] * cs, d.w[c][j] * sn);
                e[c] += t;
                if grad {
                    ex[c] += t * kj[0];
                    ey[c] += t * kj[1];
                }
            }
        }
        let i = C64::new(0.0, 1.0);
        let k = self.k;
        let (mut s, mut dx, mut dy) = ([0.0; 3], [0.0; 3], [0.0; 3]);
        for (((u, rh), sg), &ph) in d.u.iter().zip(&self.rdet).zip(&self.sdet).zip(det) {
            let w = u[0] * e[0] + u[1] * e[1] + u[2] * e[2];
            let val = (ph * w).re;
            let (gx, gy) = if grad {
                let wx = u[0] * ex[0] + u[1] * ex[1] + u[2] * ex[2];
                let wy = u[0] * ey[0] + u[1] * ey[1] + u[2] * ey[2];
                (
                    (ph * i * (wx - w * (k * rh[0]))).re,
                    (ph * i * (wy - w * (k * rh[1]))).re,
                )
            } else {
                (0.0, 0.0)
            };
            for c in 0..3 {
                s[c] += sg[c] * val;
                dx[c] += sg[c] * gx;
                dy[c] += sg[c] * gy;
            }
        }
        (s, dx, dy)
    }
}

/// Complex dot product Σ (mr + i mi)(ar + i ai) with four independent accumulators (lets the
/// compiler vectorise the reduction).
#[inline]
fn cdot(mr: &[f64], mi: &[f64], ar: &[f64], ai: &[f64]) -> C64 {
    let n = mr.len();
    let (mut re, mut im) = ([0.0f64; 4], [0.0f64; 4]);
    let chunks = n / 4;
    for c in 0..chunks {
        let b = 4 * c;
        for l in 0..4 {
            let (p, q, r, s) = (mr[b + l], mi[b + l], ar[b + l], ai[b + l]);
            re[l] += p * r - q * s;
            im[l] += p * s + q * r;
        }
    }
    let mut out = C64::new(re[0] + re[1] + re[2] + re[3], im[0] + im[1] + im[2] + im[3]);
    for j in 4 * chunks..n {
        out += C64::new(mr[j] * ar[j] - mi[j] * ai[j], mr[j] * ai[j] + mi[j] * ar[j]);
    }
    out
}

/// Three complex dot products of one matrix row with three vectors in one pass over the row.
#[inline]
fn cdot3(mr: &[f64], mi: &[f64], v: [(&[f64], &[f64]); 3]) -> [C64; 3] {
    let n = mr.len();
    let mut re = [[0.0f64; 4]; 3];
    let mut im = [[0.0f64; 4]; 3];
    let chunks = n / 4;
    for c in 0..chunks {
        let b = 4 * c;
        for l in 0..4 {
            let (p, q) = (mr[b + l], mi[b + l]);
            for t in 0..3 {
                let (r, s) = (v[t].0[b + l], v[t].1[b + l]);
                re[t][l] += p * r - q * s;
                im[t][l] += p * s + q * r;
            }
        }
    }
    let mut out = [C64::new(0.0, 0.0); 3];
    for t in 0..3 {
        out[t] = C64::new(re[t].iter().sum(), im[t].iter().sum());
        for j in 4 * chunks..n {
            let (r, s) = (v[t].0[j], v[t].1[j]);
            out[t] += C64::new(mr[j] * r - mi[j] * s, mr[j] * s + mi[j] * r);
        }
    }
    out
}

/// How far the point dipole is off for a bead of diameter `d_nm` (nm) and real index `n`:
/// the relative error of its normalised maximum sensitivity
/// (∂Sx/∂x)max(d, n)/(∂Sx/∂x)max(110 nm polystyrene) (paper Fig. 3c, Sec. 3.2), against the
/// focused-beam Mie tier in one beam:
/// err = [α(d, n)/α(110, PS)] / [M(d, n)/M(110, PS)] − 1, with M the Mie tier's maximum
/// sensitivity (default grid) and α the static Clausius–Mossotti polarisability (µm³): the
/// point dipole's normalised sensitivity is α(d, n)/α(110, PS) exactly, Mie's is the M ratio.
/// Dimensionless; about 0.2 s in a release build (two Mie responses). Pure: the simulator's
/// domain check (`instrument::sim::domain`) remembers results in a bounded memo it owns.
pub fn point_dipole_error(optics: &impl OpticsArg, d_nm: f64, n: f64) -> Result<f64, OpticsError> {
    let optics = optics.valid()?;
    let optics: &ValidOptics = &optics;
    let reference = max_sensitivity_per_alpha(
        optics,
        super::params::REF_BEAD_D_NM,
        super::params::REF_BEAD_N,
    )?;
    Ok(reference / max_sensitivity_per_alpha(optics, d_nm, n)? - 1.0)
}

/// M(d, n)/α(d, n): the Mie tier's maximum sensitivity (∂Sx/∂x)max (µm⁻¹, default grid, in the
/// beam of `optics`: [`MieBeamSpec::of_beam`]) per
/// unit static polarisability α (µm³), the two factors of [`point_dipole_error`] (paper
/// Fig. 3c, Sec. 3.2); µm⁻⁴. M is signed, the extreme of the central lobe
/// ([`MieBeam::extreme_sensitivity_x`]): for n below the medium's both M and α are negative,
/// and M/α is the same positive shape factor as for n above it. One Mie response, about
/// 0.05–0.1 s in a release build. An error when n equals the medium's index (α = 0).
pub fn max_sensitivity_per_alpha(
    optics: &impl OpticsArg,
    d_nm: f64,
    n: f64,
) -> Result<f64, OpticsError> {
    let optics = optics.valid()?;
    let optics: &ValidOptics = &optics;
    let alpha = super::rayleigh::alpha_um3(d_nm, n, optics.n_medium);
    if alpha == 0.0 {
        return Err(OpticsError::Invalid(format!(
            "point_dipole_error: n = {n} equals the medium index {}: α = 0",
            optics.n_medium
        )));
    }
    let m = MieBeam::new(optics, d_nm, C64::new(n, 0.0), MieBeamSpec::of_beam(optics))?
        .extreme_sensitivity_x(alpha)
        .0;
    Ok(m / alpha)
}

/// QPD signals of a point dipole (a sphere of diameter `d_nm`, index `n`, static polarisability
/// α) displaced `pos_um` (µm) from the focus, in the beam of `optics`: the paper's
/// paraxial Rayleigh model (suppl. S2, [`super::rayleigh::response`], `det.polarization`
/// honoured) or the aplanatic vector focus (docs/physics.md §10; always vectorial, so
/// `det.polarization` has no effect there). Normalised to the beam power, dimensionless.
pub fn dipole_response_in_beam(
    optics: &impl OpticsArg,
    det: &DetectorModel,
    pos_um: [f64; 3],
    d_nm: f64,
    n: f64,
) -> Result<super::rayleigh::Signals, OpticsError> {
    let optics = optics.valid()?;
    let optics: &ValidOptics = &optics;
    if let DipoleTier::ParaxialRayleigh = optics.beam().dipoles() {
        return super::rayleigh::response(optics, det, pos_um, d_nm, n);
    }
    super::rayleigh::check_particle(d_nm, n)?;
    for (name, v) in [("x", pos_um[0]), ("y", pos_um[1]), ("z", pos_um[2])] {
        check_range(name, v, -1e4, 1e4)?;
    }
    let rho = pos_um[0].hypot(pos_um[1]);
    let (d0, n0) = (DIPOLE_D_NM, DIPOLE_N);
    let dipole = |grids: MieBeamSpec| MieBeamSpec {
        detector: *det,
        amplitudes: Amplitudes::Dipole,
        ..grids.with_beam_of(optics)
    };
    let spec = dipole(MieBeamSpec::default());
    let spec = if rho <= grid_reach_um(optics, &spec, pos_um[2]) {
        spec
    } else {
        dipole(MieBeamSpec::for_reach(optics, rho, pos_um[2]))
    };
    let o = valid_optics_for_reach(optics, rho);
    let s =
        MieBeam::new(&o, d0, C64::new(n0, 0.0), spec)?.response(pos_um[0], pos_um[1], pos_um[2])?;
    let a = super::rayleigh::alpha_um3(d_nm, n, optics.n_medium)
        / super::rayleigh::alpha_um3(d0, n0, optics.n_medium);
    Ok(super::rayleigh::Signals {
        sx: a * s[0],
        sy: a * s[1],
        sz: a * s[2],
    })
}

/// Which scatterer model [`max_sensitivity_in_beam`] evaluates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum SphereModel {
    /// Point dipole of the sphere's static polarisability (paper Sec. 3.2).
    Dipole,
    /// Sphere rule of `n_r` radial orders of dipoles over the volume (suppl. S6).
    FiniteSize { n_r: usize },
    /// Exact Lorenz–Mie sphere (§9).
    Mie,
}

/// Maximum sensitivity (∂Sx/∂x)max (µm⁻¹) of a sphere of diameter `d_nm` (nm) and real index `n`
/// at its best focus, and that axial displacement z (µm), in the beam of `optics`
/// (paper Fig. 3c; the height optimised as in suppl. S5): for `Beam::Paraxial` the paper's
/// Rayleigh tier (suppl. S3/S6) — the Mie model then in §9's beam —, for `Beam::Vector` the
/// aplanatic vector focus (docs/physics.md §10), every model in it. Dimensionless signals per
/// beam power. Errors: invalid optics, a sphere out of range, n equal to the medium's index.
pub fn max_sensitivity_in_beam(
    optics: &impl OpticsArg,
    d_nm: f64,
    n: f64,
    model: SphereModel,
) -> Result<(f64, f64), OpticsError> {
    super::rayleigh::check_particle(d_nm, n)?;
    let optics = optics.valid()?;
    let optics: &ValidOptics = &optics;
    let alpha = super::rayleigh::alpha_um3(d_nm, n, optics.n_medium);
    match (model, optics.beam().dipoles()) {
        (SphereModel::Mie, _) => {
            Ok(
                MieBeam::new(optics, d_nm, C64::new(n, 0.0), MieBeamSpec::of_beam(optics))?
                    .extreme_sensitivity_x(alpha),
            )
        }
        (SphereModel::Dipole | SphereModel::FiniteSize { .. }, DipoleTier::ParaxialRayleigh) => {
            let det = Detection::new(optics, &DetectorModel::default())?;
            let (size, n_r) = match model {
                SphereModel::FiniteSize { n_r } => (Some(d_nm), n_r),
                _ => (None, super::finite_size::DEFAULT_N_R),
            };
            let (s, z) = super::finite_size::max_sensitivity_unit(&det, size, n_r);
            Ok((s * alpha, z))
        }
        (SphereModel::Dipole | SphereModel::FiniteSize { .. }, DipoleTier::AngularSpectrum) => {
            // the vector beam's point dipole: a 1 nm sphere's Mie response per unit α
            let (d0, n0) = (DIPOLE_D_NM, DIPOLE_N);
            let a0 = super::rayleigh::alpha_um3(d0, n0, optics.n_medium);
            let spec = MieBeamSpec {
                amplitudes: Amplitudes::Dipole,
                ..MieBeamSpec::of_beam(optics)
            };
            let dip = MieBeam::new(optics, d0, C64::new(n0, 0.0), spec)?;
            let pts = match model {
                SphereModel::FiniteSize { n_r } => {
                    super::finite_size::sphere_points(d_nm * 1e-3, n_r)
                }
                _ => vec![([0.0; 3], 1.0)],
            };
            let (s, z) = super::finite_size::best_focus(|z| {
                pts.iter()
                    .map(|(o, w)| w * dip.eval(o[0], o[1], z + o[2], true).1[0])
                    .sum()
            });
            Ok((s * alpha / a0, z))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The point dipole's factorised response (incident field, then one 3-vector product per
    /// detection node) equals the pair-matrix sum it replaces, signal and analytic derivatives,
    /// in the aplanatic vector beam with a misaligned QPD and in §9's beam, at and off focus.
    #[test]
    fn factorised_dipole_equals_the_pair_matrix() {
        use crate::optics::rayleigh::Misalignment;
        for (beam, mis) in [
            (
                super::super::params::Beam::Vector,
                Some(Misalignment::default()),
            ),
            (super::super::params::Beam::Paraxial, None),
        ] {
            let o = ValidOptics::new(Optics {
                beam,
                ..Optics::default()
            })
            .unwrap();
            let spec = MieBeamSpec {
                amplitudes: Amplitudes::Dipole,
                detector: DetectorModel {
                    polarization: false,
                    misalignment: mis,
                },
                ..MieBeamSpec::of_beam(&o)
            };
            let n = C64::new(1.572, 0.0);
            let fast = MieBeam::build(&o, 110.0, n, spec, true).unwrap();
            let slow = MieBeam::build(&o, 110.0, n, spec, false).unwrap();
            assert!(fast.dipole.is_some() && slow.dipole.is_none() && fast.m_re.is_empty());
            let peak = slow.response(0.27, 0.0, 0.0).unwrap()[0].abs();
            for (x, y, z) in [
                (0.0, 0.0, 0.0),
                (0.27, -0.11, 0.0),
                (-0.4, 0.6, 0.3),
                (1.1, 0.2, -0.5),
            ] {
                let (a, b) = (fast.eval(x, y, z, true), slow.eval(x, y, z, true));
                for c in 0..3 {
                    for (p, q, what) in [
                        (a.0[c], b.0[c], "S"),
                        (a.1[c], b.1[c], "∂x"),
                        (a.2[c], b.2[c], "∂y"),
                    ] {
                        assert!(
                            (p - q).abs()
                                <= 1e-12 * peak.max(q.abs()) * if what == "S" { 1.0 } else { 20.0 },
                            "{beam:?} ({x}, {y}, {z}) channel {c} {what}: {p} vs {q}"
                        );
                    }
                }
            }
        }
    }

    /// The BH-basis bracket with dipole amplitudes equals the dipole field ê − (ê·r̂) r̂ times
    /// S₁, for any pair of directions (an independent formula for the bases).
    #[test]
    fn bh_bases_reproduce_the_dipole_projection() {
        let s = C64::new(0.3, -1.7);
        let dirs: [(f64, f64); 6] = [
            (0.3, 0.2),
            (1.0, -2.0),
            (0.01, 3.0),
            (1.1, 0.7),
            (0.0, 0.0),
            (0.5, 4.0),
        ];
        for &(t1, p1) in &dirs {
            for &(t2, p2) in &dirs {
                let kh = [t1.sin() * p1.cos(), t1.sin() * p1.sin(), t1.cos()];
                let rh = [t2.sin() * p2.cos(), t2.sin() * p2.sin(), t2.cos()];
                let e = pupil_pol(kh[0], kh[1], kh[2]);
                assert!(dot(e, kh).abs() < 1e-15 && (dot(e, e) - 1.0).abs() < 1e-14);
                let c = dot(kh, rh);
                let v = scattering_vector(kh, e, rh, s, s * c);
                let er = dot(e, rh);
                for a in 0..3 {
                    let want = s * (e[a] - er * rh[a]);
                    assert!((v[a] - want).norm() < 1e-13, "{t1} {p1} {t2} {p2}: {a}");
                }
            }
        }
    }

    #[test]
    fn cdot_matches_naive_sum() {
        let n = 13;
        let mr: Vec<f64> = (0..n).map(|i| (i as f64 * 0.37).sin()).collect();
        let mi: Vec<f64> = (0..n).map(|i| (i as f64 * 0.71).cos()).collect();
        let ar: Vec<f64> = (0..n).map(|i| (i as f64 * 1.3).cos()).collect();
        let ai: Vec<f64> = (0..n).map(|i| (i as f64 * 0.2).sin()).collect();
        let want: C64 = (0..n)
            .map(|j| C64::new(mr[j], mi[j]) * C64::new(ar[j], ai[j]))
            .sum();
        assert!((cdot(&mr, &mi, &ar, &ai) - want).norm() < 1e-14);
    }
}
