//! Calculators from the supplement: scattered power (S1), trap depth (S3), the index
//! correction (main text eq. nCor) and bead mass.

use super::beam::OpticsArg;
use super::params::{check_above, check_range, OpticsError};
use super::rayleigh::clausius_mossotti;
use std::f64::consts::PI;

/// Speed of light in vacuum, m/s.
pub const C0: f64 = 2.998e8;
/// Boltzmann constant, J/K.
pub const KB: f64 = 1.380_649e-23;
/// Dalton in grams.
pub const DALTON_G: f64 = 1.660_539_066_6e-24;
/// Default temperature for kT, K (room temperature, 22 °C).
pub const ROOM_T_K: f64 = 295.15;

/// Ratio of scattered to beam power for a Rayleigh sphere at the focus (suppl. S1), with w0 the
/// **1/e² intensity radius** (the convention of every other formula in this crate):
///   P_scat = I0·σ, σ = (8π/3) k⁴ CM² r⁶ (Rayleigh cross-section), k = 2π n_s/λ,
///   I0 = 2P/(π w0²) (peak of a Gaussian of 1/e² radius w0), so
///   P_scat/P_beam = (16/3) k⁴ CM² r⁶ / w0².  Dimensionless (r, w0 in µm, k in 1/µm).
/// CM = (m²−1)/(m²+2), m = n/n_s. The supplement (S1, the equations after "We can express
/// P_beam as") integrates I0·e^{−(x²+y²)/w0²}, i.e. takes w0 as a 1/e intensity radius, and gets
/// half this value: see [`p_scat_ratio_paper`] (2.35e-5 for the 110 nm reference bead, its
/// "≈ 2×10⁻⁵"; 4.70e-5 here).
pub fn p_scat_ratio(optics: &impl OpticsArg, d_nm: f64, n: f64) -> Result<f64, OpticsError> {
    Ok(2.0 * p_scat_ratio_paper(optics, d_nm, n)?)
}

/// The supplement's S1 value in its own convention (w0 read as the 1/e intensity radius, P_beam
/// = I0 π w0²): P_scat/P_beam = (8/3) k⁴ CM² r⁶ / w0², half of [`p_scat_ratio`]. Kept to
/// reproduce the paper's "≈ 2×10⁻⁵" and "exceed 300 nm before … 1 %".
pub fn p_scat_ratio_paper(optics: &impl OpticsArg, d_nm: f64, n: f64) -> Result<f64, OpticsError> {
    let optics = optics.valid()?;
    check_range("d_nm", d_nm, 0.0, 20000.0)?;
    check_range("n", n, 1.0, 5.0)?;
    let k = optics.k_per_um();
    let r = d_nm * 0.5e-3;
    Ok(
        8.0 / 3.0 * k.powi(4) * clausius_mossotti(n, optics.n_medium).powi(2) * r.powi(6)
            / optics.w0_um().powi(2),
    )
}

/// Shape for the trap-depth calculator.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TrapShape {
    Sphere,
    /// Infinite cylinder in the focal plane (a fibril), diameter d.
    Cylinder,
}

/// Depth of the gradient-force potential at the focus in units of kT (suppl. S3), positive for
/// a particle attracted to the focus.
///
/// Sphere (suppl. S3): U = P n_s² d³ CM / (2 w0² c_s).
/// Cylinder (suppl. S3, fibril as a line of spheres with volume factor 3/2 per length d):
///   U = (3/4) P n_s² d² CM √(π/2) / (w0 c_s).
/// The supplement's last line prints 3 n_s²/(w0 c_s) · … · √(π/2) w0; integrating its own
/// previous line gives the form above (its prefactor is 4 w0 larger and not an energy), see
/// docs/physics.md. c_s = c0/n_s as in Fig. S3's caption; P = `optics.power_mw`.
/// Both keep the paper's n_s²: S3 converts power to field without the medium's n_s²
/// (I = ε0 c_s|E|²/2), so the n_s² of the polarisability survives; the textbook dipole potential
/// P d³ CM/(2 w0² c_s) is n_s² (1.777 in water) smaller. The peak intensity is the 1/e² one,
/// 2P/(π w0²), as everywhere in this crate (docs/physics.md §6, "Where the trap formula keeps the
/// paper's factors").
pub fn trap_depth_kt(
    optics: &impl OpticsArg,
    shape: TrapShape,
    d_nm: f64,
    n: f64,
    temperature_k: f64,
) -> Result<f64, OpticsError> {
    let optics = optics.valid()?;
    check_range("d_nm", d_nm, 0.0, 20000.0)?;
    check_range("n", n, 1.0, 5.0)?;
    check_above("temperature_k", temperature_k, 0.0)?;
    let p = optics.power_mw * 1e-3; // W
    let ns = optics.n_medium;
    let cs = C0 / ns;
    let d = d_nm * 1e-9;
    let w0 = optics.w0_nm * 1e-9;
    let cm = clausius_mossotti(n, ns);
    let u = match shape {
        TrapShape::Sphere => p * ns * ns * d.powi(3) * cm / (2.0 * w0 * w0 * cs),
        TrapShape::Cylinder => 0.75 * p * ns * ns * d * d * cm * (PI / 2.0).sqrt() / (w0 * cs),
    };
    Ok(u / (KB * temperature_k))
}

/// Refractive-index correction (main text eq. nCor): the sensitivity of an object of index
/// `n_obj` relative to a reference of index `n_ref` and the same volume, in medium `n_medium`.
pub fn n_corr(n_obj: f64, n_ref: f64, n_medium: f64) -> Result<f64, OpticsError> {
    check_range("n_obj", n_obj, 1.0, 5.0)?;
    check_range("n_ref", n_ref, 1.0, 5.0)?;
    check_range("n_medium", n_medium, 1.0, 3.0)?;
    let r = clausius_mossotti(n_ref, n_medium);
    if r.abs() < 1e-12 {
        return Err(OpticsError::Invalid(format!(
            "n_ref = {n_ref} equals n_medium = {n_medium}: a reference bead without contrast cannot calibrate"
        )));
    }
    Ok(clausius_mossotti(n_obj, n_medium) / r)
}

/// Mass of a sphere of diameter `d_nm` and density `density_g_cm3`, in kDa.
pub fn sphere_mass_kda(d_nm: f64, density_g_cm3: f64) -> Result<f64, OpticsError> {
    check_range("d_nm", d_nm, 0.0, 1e6)?;
    check_above("density_g_cm3", density_g_cm3, 0.0)?;
    let v_cm3 = PI / 6.0 * (d_nm * 1e-7).powi(3);
    Ok(v_cm3 * density_g_cm3 / DALTON_G * 1e-3)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_numbers() {
        let o = super::super::params::Optics::default();
        // S1: "≈ 2×10⁻⁵" for the 110 nm polystyrene reference bead, in the paper's 1/e convention
        let r = p_scat_ratio_paper(&o, 110.0, 1.572).unwrap();
        assert!((r - 2.35e-5).abs() < 0.01e-5, "{r:e}");
        // 1/e² convention, written out: k = 2π·1.333/1.064 µm⁻¹ = 7.871697 µm⁻¹,
        // CM = (m²−1)/(m²+2) with m = 1.572/1.333: 0.1152364; r = 0.055 µm, w0 = 0.4 µm:
        // (16/3)·k⁴·CM²·r⁶/w0² = 4.70444e-5 (twice the paper's value).
        let r2 = p_scat_ratio(&o, 110.0, 1.572).unwrap();
        assert!((r2 / 4.70444e-5 - 1.0).abs() < 1e-5, "{r2:e}");
        // 1 % of the beam at 110·(1e-2/4.70444e-5)^(1/6) = 268.7 nm in the 1/e² convention
        let d2 = 110.0 * (1e-2 / r2).powf(1.0 / 6.0);
        assert!((d2 - 268.72).abs() < 0.05, "{d2}");
        // S1: "would have to exceed 300 nm before … 1%": ratio crosses 1e-2 near 300 nm
        let d1 = 110.0 * (1e-2 / r).powf(1.0 / 6.0);
        assert!((d1 - 300.0).abs() < 10.0, "{d1}");
        // S3: collagen fibrils up to 150 nm stay below 1 kT. The closed form written out with
        // SI values (P = 0.13 mW, n_s = 1.333, n = 1.414, d = 150 nm, w0 = 400 nm, c0 exact,
        // T = 295.15 K): U = (3/4) P n_s² d² CM √(π/2) / (w0 c_s) / (k_B T) = 0.53409 kT;
        // the code's c0 = 2.998e8 m/s differs from the exact value by 2.6e-5 relative.
        let u = trap_depth_kt(&o, TrapShape::Cylinder, 150.0, 1.414, ROOM_T_K).unwrap();
        let (p, ns, n, d, w0) = (0.13e-3, 1.333f64, 1.414f64, 150e-9f64, 400e-9);
        let cm = (n * n - ns * ns) / (n * n + 2.0 * ns * ns);
        let want = 0.75 * p * ns * ns * d * d * cm * (PI / 2.0).sqrt()
            / (w0 * (299_792_458.0 / ns))
            / (1.380_649e-23 * 295.15);
        assert!((u / want - 1.0).abs() < 5e-5, "{u} vs {want}");
        assert!(u < 1.0, "{u}");
        // closed forms: sphere ∝ d³, cylinder ∝ d²
        let a = trap_depth_kt(&o, TrapShape::Sphere, 50.0, 1.572, 300.0).unwrap();
        let b = trap_depth_kt(&o, TrapShape::Sphere, 100.0, 1.572, 300.0).unwrap();
        assert!((b / a - 8.0).abs() < 1e-12);
    }

    #[test]
    fn n_corr_limits() {
        assert_eq!(n_corr(1.572, 1.572, 1.333).unwrap(), 1.0);
        assert_eq!(n_corr(1.333, 1.572, 1.333).unwrap(), 0.0);
        assert!(n_corr(1.414, 1.57, 1.333).unwrap() < 0.4);
        let e = n_corr(1.5, 1.333, 1.333).unwrap_err().to_string();
        assert!(e.contains("without contrast"), "{e}");
        let e = n_corr(f64::NAN, 1.57, 1.333).unwrap_err().to_string();
        assert!(e.contains("n_obj"), "{e}");
    }

    #[test]
    fn reference_bead_mass() {
        // 110 nm polystyrene at 1.05 g/cm³: ρ π d³/6 = 7.32e-16 g = 441 MDa
        let m = sphere_mass_kda(110.0, 1.05).unwrap();
        assert!((m / 1e3 - 440.8).abs() < 0.5, "{m}");
    }
}
