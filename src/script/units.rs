//! Units of result values as the prompt prints them.
//!
//! The project's rule (docs/guide.md, "Units"): a result value's unit is in its key — a suffix
//! (`w0_nm`, `dwell_s`, `velocity_um_s`, `mu_mda_um`) — or, for the bare names positions and
//! sensitivities go by everywhere (`x`, `y`, `z`, `t`, `z_best`, `cen`, `sens`, …), printed
//! after the value: `#{x: 1.25 µm, y: -0.5 µm}`. Everything else is dimensionless (signals
//! normalised to the beam power, counts, ratios).

/// Unit suffixes of keys, longest first (a key `w0_nm` is in nm).
pub const SUFFIXES: &[(&str, &str)] = &[
    ("_mda_um", "MDa/µm"),
    ("_g_cm3", "g/cm³"),
    ("_um_s", "µm/s"),
    ("_um2", "µm²"),
    ("_per_um", "1/µm"),
    ("_deg", "°"),
    ("_mda", "MDa"),
    ("_nm", "nm"),
    ("_um", "µm"),
    ("_mw", "mW"),
    ("_ms", "ms"),
    ("_hz", "Hz"),
    ("_s", "s"),
];

/// Bare keys with a unit: positions along the axes and profiles (µm, the API's length unit),
/// the SPEC statistics of a line scan (positions, µm) and sensitivities (∂S/∂x of a signal
/// normalised to the beam power: 1/µm).
pub const BARE: &[(&str, &str)] = &[
    ("x", "µm"),
    ("y", "µm"),
    ("z", "µm"),
    ("t", "µm"),
    ("x0", "µm"),
    ("y0", "µm"),
    ("z0", "µm"),
    ("z_best", "µm"),
    ("z_lo", "µm"),
    ("z_hi", "µm"),
    ("z_err", "µm"),
    ("start_z", "µm"),
    ("stage_z", "µm"),
    ("cen", "µm"),
    ("com", "µm"),
    ("fwhm", "µm"),
    ("sens", "1/µm"),
    ("max_sens", "1/µm"),
    ("max_sens_err", "1/µm"),
    ("x_crlb", "µm"),
    ("y_crlb", "µm"),
    ("z_crlb", "µm"),
    ("u0", "µm"),
    ("u_crlb", "µm"),
    ("sens_bm", "1/µm"),
    ("sens_corr", "1/µm"),
    ("sens_x", "1/µm"),
    ("sens_y", "1/µm"),
    ("sens_x_sd", "1/µm"),
    ("seconds", "s"),
];

/// The unit a value under `key` is printed with, if the key does not already name it: bare
/// keys of [`BARE`]. `None` for suffixed keys (the key says it) and dimensionless ones.
/// A standard deviation `k_sd` and an uncertainty `k_err` have the unit of `k` (`x0_sd` and
/// `x_err` in µm, `polarization_deg_sd` in °).
pub fn printed_unit(key: &str) -> Option<&'static str> {
    let base = sd_base(key);
    BARE.iter().find(|(k, _)| *k == base).map(|(_, u)| *u)
}

/// `k` for a standard deviation's key `k_sd` or an uncertainty's `k_err`, else the key itself.
fn sd_base(key: &str) -> &str {
    key.strip_suffix("_sd")
        .or_else(|| key.strip_suffix("_err"))
        .filter(|b| !b.is_empty())
        .unwrap_or(key)
}

/// The unit of a key by the rule above (suffix or bare; `k_sd` as `k`), `None` when
/// dimensionless.
pub fn unit_of_key(key: &str) -> Option<&'static str> {
    let key = sd_base(key);
    printed_unit(key).or_else(|| {
        SUFFIXES
            .iter()
            .find(|(s, _)| key.ends_with(s) && key.len() > s.len())
            .map(|(_, u)| *u)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_name_their_units() {
        assert_eq!(unit_of_key("w0_nm"), Some("nm"));
        assert_eq!(unit_of_key("velocity_um_s"), Some("µm/s"));
        assert_eq!(unit_of_key("defocus_sq_um2"), Some("µm²"));
        assert_eq!(unit_of_key("mu_mda_um"), Some("MDa/µm"));
        assert_eq!(unit_of_key("angle_err_deg"), Some("°"));
        assert_eq!(unit_of_key("clock_s"), Some("s"));
        assert_eq!(unit_of_key("z_best"), Some("µm"));
        assert_eq!(printed_unit("w0_nm"), None, "the key says it");
        assert_eq!(unit_of_key("sx"), None);
        assert_eq!(unit_of_key("n_beads"), None);
        // a suffix alone is not a key with a unit
        assert_eq!(unit_of_key("_s"), None);
        // an uncertainty has its value's unit (fit_beads: x_err, y_err in µm)
        assert_eq!(printed_unit("x_err"), Some("µm"));
        assert_eq!(printed_unit("y_err"), Some("µm"));
        assert_eq!(printed_unit("max_sens_err"), Some("1/µm"));
        assert_eq!(
            printed_unit("weight_err"),
            None,
            "reference-bead units: a ratio"
        );
        assert_eq!(unit_of_key("mu_err_mda_um"), Some("MDa/µm"));
        assert_eq!(printed_unit("_err"), None);
        // longest suffix wins
        assert_eq!(unit_of_key("max_speed_um_s"), Some("µm/s"));
    }
}
