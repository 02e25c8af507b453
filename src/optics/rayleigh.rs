//! Rayleigh-dipole QPD response of a point scatterer (paper Sec. 2.1, suppl. S2).
//!
//! Model (suppl. S2, with the conventions of `docs/physics.md`):
//! * focal field: paraxial Gaussian beam, E_G(x) ∝ (w0/w) exp(−ρ²/w² + i k (z + ρ²/2R) − i φ_G),
//!   with 1/R(z) written as z/(z² + z_R²) so that it is 0 (not 1/0) at z = 0;
//! * far field of the beam: −i (k w0 / r) exp(i k r − k² w0² θ²/4) (θ in the exponent, as the
//!   paper writes it);
//! * dipole scattered field (k² α / r) E_G(x) exp(i k r − i k r̂·x), r̂·x exact (not paraxial);
//! * δI = ε c Re{E_scat E_beam*} (main text eq. ReEE) integrated over the detection cone with the
//!   area element r² sinθ dθ dφ (the paper's formula omits sinθ; the power through the condenser
//!   surface needs it, and the Gittes–Schmidt closed form is only recovered with it);
//! * Sx = right − left (cos φ > 0 minus cos φ < 0), Sy = top − bottom, Sz = sum; the paper's
//!   quadrant list (I+II) − (III+IV) names the same halves with clockwise numbering.
//!
//! Signals are normalised to the beam power (δP / P_tot, dimensionless). Displacements in µm:
//! (x, y, z) is the scatterer's position minus the focus; +z is downstream.
//!
//! Result, per channel c with node weights s_c(θ, φ) (±1, or the misaligned QPD's):
//!   S_c = (2 k³ α / π) (w0/w) e^{−ρ²/w²} Σ_nodes W s_c P e^{−k²w0²θ²/4} (−sin Ψ),
//!   Ψ = k z (1 − cos θ) + k ρ² / 2R − φ_G − k sinθ (x cos φ + y sin φ).
//! (P is the polarization factor 1 − cos²φ (1 − cos θ) when the vector dipole field is on, else 1.)

use super::beam::{OpticsArg, ValidOptics};
use super::params::{check_range, OpticsError};
use super::quad::{gauss_legendre, quadrant_gauss};
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// Clausius–Mossotti factor (m² − 1)/(m² + 2) with m = n_particle / n_medium.
pub fn clausius_mossotti(n_particle: f64, n_medium: f64) -> f64 {
    let m2 = (n_particle / n_medium).powi(2);
    (m2 - 1.0) / (m2 + 2.0)
}

/// Uniform-field susceptibility α = (d/2)³ (m² − 1)/(m² + 2) (suppl. S2), in µm³.
pub fn alpha_um3(d_nm: f64, n_particle: f64, n_medium: f64) -> f64 {
    (d_nm * 0.5e-3).powi(3) * clausius_mossotti(n_particle, n_medium)
}

/// Validate a particle: diameter in nm, index relative to anything physical.
pub fn check_particle(d_nm: f64, n: f64) -> Result<(), OpticsError> {
    check_range("d_nm", d_nm, 0.0, 20000.0)?;
    check_range("n", n, 1.0, 5.0)?;
    Ok(())
}

/// How the QPD departs from the ideal (Fig. 2a, Fig. 4d: Sy ~30% weaker and not fully
/// antisymmetric in the paper's instrument).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct Misalignment {
    /// Offset of the QPD centre from the beam axis in the BFP, in units of the detection-cone
    /// radius (sinΘ), along x and y.
    pub offset_x: f64,
    pub offset_y: f64,
    /// Rotation of the QPD about the beam axis, degrees.
    pub rotation_deg: f64,
    /// Relative gain of the Sy amplifier chain.
    pub gain_y: f64,
}

impl Default for Misalignment {
    /// Defaults chosen to reproduce the paper's ~30% weaker, slightly asymmetric Sy
    /// (measured in `tests/optics.rs`, stated in docs/physics.md).
    fn default() -> Self {
        Self {
            offset_x: 0.0,
            offset_y: 0.15,
            rotation_deg: 2.0,
            gain_y: 0.8,
        }
    }
}

/// Detector model: which effects shape the node weights.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct DetectorModel {
    /// Vector dipole field (effect `polarization`): beam polarised along x.
    pub polarization: bool,
    /// QPD misalignment (effect `misalignment`), None = ideal.
    pub misalignment: Option<Misalignment>,
}

/// One quadrature node over the detection cone, with everything that does not depend on the
/// scatterer position folded in.
#[derive(Debug, Clone, Copy)]
pub struct Node {
    /// sinθ cosφ, sinθ sinφ, cosθ (direction of the ray in the medium)
    pub u: f64,
    pub v: f64,
    pub c: f64,
    /// amplitude: (2 k³/π) · quadrature weight · sinθ · e^{−k²w0²θ²/4} · P(θ, φ)   [µm⁻³]
    pub amp: f64,
    /// channel weights (Sx, Sy, Sz)
    pub s: [f64; 3],
    /// quadrature weight × sinθ (area element / r²), for terms without the beam amplitude
    pub wq: f64,
    /// |ê_scat|² = 1 − sin²θ cos²φ with the vector dipole field, else 1 (for |E_scat|² terms)
    pub pol_ss: f64,
}

/// The detection-cone quadrature for given optics and detector model.
#[derive(Debug, Clone)]
pub struct Detection {
    pub nodes: Vec<Node>,
    pub k: f64,
    pub w0: f64,
    pub z_r: f64,
    /// True when the nodes come in mirror quartets (u, v), (−u, v), (u, −v), (−u, −v) with
    /// equal weights, amplitudes and cos θ and channel weights (sign u, sign v, 1): the ideal
    /// QPD's product rule, with or without the vector dipole field (whose factor depends on
    /// cos²φ only). The template builder then sums a quarter of the nodes
    /// (`optics::template::plane_grid`).
    pub mirror_symmetric: bool,
}

impl Detection {
    /// Build the nodes. Ideal QPD: Gauss–Legendre in θ ∈ [0, Θ] (`optics.n_theta`) and in φ over
    /// each of the four quadrants (`optics.n_phi` each), so the sign discontinuities fall on rule
    /// boundaries and the rule converges exponentially. Misaligned QPD: the same product rule in
    /// polar coordinates centred on the *QPD's* cross (φ' per quadrant, ρ' from the cross to the
    /// edge of the detection disk along each φ'), with the measure sinθ dθ dφ = du dv / cosθ
    /// (u, v = sinθ cosφ, sinθ sinφ), so the shifted and rotated boundaries are again rule
    /// boundaries.
    pub fn new(optics: &impl OpticsArg, det: &DetectorModel) -> Result<Self, OpticsError> {
        let optics = optics.valid()?;
        let k = optics.k_per_um();
        let w0 = optics.w0_um();
        let theta_max = optics.theta_max();
        let sin_max = theta_max.sin();
        let mut nodes = Vec::with_capacity(4 * optics.n_theta * optics.n_phi);
        let mut push = |st: f64, ct: f64, t: f64, cp: f64, sp: f64, weight: f64, s: [f64; 3]| {
            // weight = measure of sinθ dθ dφ carried by this node
            let gauss = (-(k * w0 * t).powi(2) / 4.0).exp();
            let pol = if det.polarization {
                1.0 - cp * cp * (1.0 - ct)
            } else {
                1.0
            };
            let (u, v) = (st * cp, st * sp);
            let pol_ss = if det.polarization { 1.0 - u * u } else { 1.0 };
            let amp = 2.0 * k.powi(3) / PI * weight * gauss * pol;
            nodes.push(Node {
                u,
                v,
                c: ct,
                amp,
                s,
                wq: weight,
                pol_ss,
            });
        };
        match det.misalignment {
            None => {
                let (th, wth) = gauss_legendre(optics.n_theta, 0.0, theta_max);
                for (ph, wph) in quadrant_gauss(optics.n_phi) {
                    for (&t, &wt) in th.iter().zip(&wth) {
                        let (st, ct) = t.sin_cos();
                        for (&p, &wp) in ph.iter().zip(&wph) {
                            let (sp, cp) = p.sin_cos();
                            push(
                                st,
                                ct,
                                t,
                                cp,
                                sp,
                                wt * wp * st,
                                [cp.signum(), sp.signum(), 1.0],
                            );
                        }
                    }
                }
            }
            Some(m) => {
                let (ox, oy) = (m.offset_x, m.offset_y);
                if !(ox.is_finite() && oy.is_finite() && ox.hypot(oy) < 0.95) {
                    return Err(OpticsError::Invalid(format!(
                        "misalignment offset ({ox}, {oy}) puts the QPD cross outside the beam: |offset| must be < 0.95 of the cone radius"
                    )));
                }
                let (rs, rc) = m.rotation_deg.to_radians().sin_cos();
                // disk centre in detector coordinates (d = R·n − o with n the normalised BFP point)
                let (cx, cy) = (-ox, -oy);
                for (ph, wph) in quadrant_gauss(optics.n_phi) {
                    for (&p, &wp) in ph.iter().zip(&wph) {
                        let (sp_d, cp_d) = p.sin_cos();
                        let ec = cp_d * cx + sp_d * cy;
                        let t_edge = ec + (ec * ec - (cx * cx + cy * cy) + 1.0).sqrt();
                        let (rr, wr) = gauss_legendre(optics.n_theta, 0.0, t_edge);
                        for (&r, &w) in rr.iter().zip(&wr) {
                            // detector point → normalised BFP point (rotate back, shift)
                            let (dx, dy) = (r * cp_d + ox, r * sp_d + oy);
                            let (un, vn) = (rc * dx - rs * dy, rs * dx + rc * dy);
                            let st = (sin_max * un.hypot(vn)).min(1.0);
                            let ct = (1.0 - st * st).max(1e-12).sqrt();
                            let t = st.asin();
                            let (cp, sp) = if st > 0.0 {
                                (un / un.hypot(vn), vn / un.hypot(vn))
                            } else {
                                (1.0, 0.0)
                            };
                            let weight = sin_max * sin_max * r * w * wp / ct;
                            push(
                                st,
                                ct,
                                t,
                                cp,
                                sp,
                                weight,
                                [cp_d.signum(), m.gain_y * sp_d.signum(), 1.0],
                            );
                        }
                    }
                }
            }
        }
        Ok(Self {
            nodes,
            k,
            w0,
            z_r: optics.z_r_um(),
            mirror_symmetric: det.misalignment.is_none(),
        })
    }

    /// Beam quantities at axial displacement z (µm): (w(z), 1/R(z), Gouy phase).
    #[inline]
    pub fn beam_at(&self, z: f64) -> (f64, f64, f64) {
        let w = self.w0 * (1.0 + (z / self.z_r).powi(2)).sqrt();
        let inv_r = z / (z * z + self.z_r * self.z_r);
        (w, inv_r, (z / self.z_r).atan())
    }

    /// Response per unit polarisability (multiply by α in µm³): (Sx, Sy, Sz) and their
    /// derivatives with respect to x and y, at displacement (x, y, z) µm.
    pub fn response_unit(&self, x: f64, y: f64, z: f64) -> ([f64; 3], [f64; 3], [f64; 3]) {
        let (w, inv_r, gouy) = self.beam_at(z);
        let rho2 = x * x + y * y;
        let env = (self.w0 / w) * (-rho2 / (w * w)).exp();
        let mut s = [0.0; 3];
        let mut dx = [0.0; 3];
        let mut dy = [0.0; 3];
        if env == 0.0 || !env.is_finite() {
            return (s, dx, dy);
        }
        let k = self.k;
        let base = k * z + 0.5 * k * rho2 * inv_r - gouy;
        // dΨ/dx = k x / R − k u ; d env/dx = −2x/w² env
        let (gx, gy) = (-2.0 * x / (w * w), -2.0 * y / (w * w));
        for n in &self.nodes {
            let psi = base - k * (x * n.u + y * n.v + z * n.c);
            let (sp, cp) = psi.sin_cos();
            let a = n.amp;
            let val = -sp * a;
            let dpsi_x = k * x * inv_r - k * n.u;
            let dpsi_y = k * y * inv_r - k * n.v;
            for c in 0..3 {
                let sc = n.s[c];
                s[c] += sc * val;
                dx[c] += sc * a * (-sp * gx - cp * dpsi_x);
                dy[c] += sc * a * (-sp * gy - cp * dpsi_y);
            }
        }
        for c in 0..3 {
            s[c] *= env;
            dx[c] *= env;
            dy[c] *= env;
        }
        (s, dx, dy)
    }
}

/// Signals of one scatterer.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Signals {
    pub sx: f64,
    pub sy: f64,
    pub sz: f64,
}

/// QPD response (Sx, Sy, Sz), normalised to the beam power, of a sphere of diameter `d_nm` and
/// index `n` at displacement (x, y, z) µm from the focus (suppl. S2).
pub fn response(
    optics: &impl OpticsArg,
    det: &DetectorModel,
    pos_um: [f64; 3],
    d_nm: f64,
    n: f64,
) -> Result<Signals, OpticsError> {
    check_particle(d_nm, n)?;
    for (name, v) in [("x", pos_um[0]), ("y", pos_um[1]), ("z", pos_um[2])] {
        check_range(name, v, -1e4, 1e4)?;
    }
    let optics = optics.valid()?;
    let optics: &ValidOptics = &optics;
    let d = Detection::new(optics, det)?;
    let a = alpha_um3(d_nm, n, optics.n_medium);
    let (s, _, _) = d.response_unit(pos_um[0], pos_um[1], pos_um[2]);
    Ok(Signals {
        sx: a * s[0],
        sy: a * s[1],
        sz: a * s[2],
    })
}

/// Dawson's integral F(x) = e^{−x²} ∫₀ˣ e^{t²} dt, by Rybicki's method (Numerical Recipes
/// sec. 6.10) with step h = 0.25, whose error ~exp(−(π/2h)²) ≈ 1e-17, and a series for |x| < 0.2.
pub fn dawson(x: f64) -> f64 {
    let ax = x.abs();
    if ax < 0.2 {
        let x2 = x * x;
        // Σ (−2x²)^n / (2n+1)!! · x, to n = 9 (term < 1e-17 for |x| < 0.2)
        let (mut term, mut sum) = (x, x);
        for n in 1..10 {
            term *= -2.0 * x2 / (2 * n + 1) as f64;
            sum += term;
        }
        return sum;
    }
    const H: f64 = 0.25;
    const NMAX: i32 = 14;
    let n0 = 2 * ((0.5 * ax / H + 0.5) as i32);
    let xp = ax - n0 as f64 * H;
    let mut e1 = (2.0 * xp * H).exp();
    let e2 = e1 * e1;
    let mut d1 = n0 as f64 + 1.0;
    let mut d2 = d1 - 2.0;
    let mut sum = 0.0;
    for i in 0..NMAX {
        let c = (-((2 * i + 1) as f64 * H).powi(2)).exp();
        sum += c * (e1 / d1 + 1.0 / (d2 * e1));
        d1 += 2.0;
        d2 -= 2.0;
        e1 *= e2;
    }
    (1.0 / PI.sqrt()) * (-xp * xp).exp() * sum * x.signum()
}

/// Closed form of the lateral response in the paraxial, full-collection limit at z = 0, y = 0
/// (Gittes & Schmidt, Opt. Lett. 23, 7 (1998); derived in docs/physics.md):
///   Sx / P = (16/√π) (k α / w0²) e^{−x²/w0²} F(x/w0),   F = Dawson's integral.
/// Slope at the origin: (16/√π) k α / w0³. Units: k in µm⁻¹, α in µm³, x and w0 in µm.
pub fn gittes_schmidt_sx(k: f64, alpha: f64, w0: f64, x: f64) -> f64 {
    16.0 / PI.sqrt() * k * alpha / (w0 * w0) * (-(x / w0).powi(2)).exp() * dawson(x / w0)
}
