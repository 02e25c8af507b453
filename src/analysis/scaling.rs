//! The two scalings every measurement shares (Sec. 3.2): the contrast of an object against the
//! reference bead (eq. nCor, Clausius–Mossotti) and the mass of a volume at a density. A leaf:
//! the template (reference-bead mass), the bead model (section weights) and `quantities` (which
//! re-exports these) all read them from here.
//!
//! Units: indices dimensionless, volumes nm³, densities g/cm³, masses kDa.

use super::{check_range, AnalysisError, Result};

/// Avogadro's number: daltons per gram.
pub const DA_PER_G: f64 = 6.022_140_76e23;
/// Clausius–Mossotti factor (m² − 1)/(m² + 2) with m = n/n_medium.
pub fn clausius_mossotti(n: f64, n_medium: f64) -> f64 {
    let m2 = (n / n_medium).powi(2);
    (m2 - 1.0) / (m2 + 2.0)
}

/// eq. nCor: n_corr = CM(n_obj)/CM(n_ref), CM(n) = ((n/n_s)² − 1)/((n/n_s)² + 2).
/// Errors: indices outside [1, 4], n_medium outside [1, 3], a reference with n_ref ≤ n_medium
/// (zero or negative contrast: no calibration possible). n_obj = n_medium gives 0 (invisible);
/// n_obj < n_medium a negative factor (the object lowers the signal).
pub fn n_corr(n_obj: f64, n_ref: f64, n_medium: f64) -> Result<f64> {
    check_range("n_obj", n_obj, 1.0, 4.0)?;
    check_range("n_ref", n_ref, 1.0, 4.0)?;
    check_range("n_medium", n_medium, 1.0, 3.0)?;
    if n_ref <= n_medium {
        return Err(AnalysisError::OutOfRange {
            name: "n_ref",
            value: n_ref,
            allowed: format!("n_ref > n_medium = {n_medium} (the reference must scatter)"),
        });
    }
    Ok(clausius_mossotti(n_obj, n_medium) / clausius_mossotti(n_ref, n_medium))
}

/// Mass (kDa) of a volume (nm³) at a density (g/cm³): V·10⁻²¹ cm³/nm³·ρ·N_A / 1000.
pub fn mass_kda(volume_nm3: f64, density_g_cm3: f64) -> f64 {
    volume_nm3 * 1e-21 * density_g_cm3 * DA_PER_G / 1000.0
}
