//! The config tables that are not devices: `[sandbox]` (the script's limits), `[session]`
//! (where scans go) and `[optics]` (the set-up's optics at start-up). Parsed with the rest of
//! `bfpscope.toml` by [`super::Config`], the file's one owner: an unknown key is an error here
//! as in `[stage]`.
//!
//! ```toml
//! [sandbox]
//! max_operations = 500000000   # a runaway loop stops after about ten seconds
//!
//! [session]
//! data_dir = "/data/tweezers"  # default: ./bfpscope_data/YYYY-MM-DD/
//!
//! [optics]                     # the keys of set_optics (nm, mW); unset keys keep the defaults
//! wavelength_nm = 1064.0
//! na = 1.2
//! beam = "vector"
//! ```

use crate::optics::{Beam, Optics, ValidOptics};
use serde::{Deserialize, Serialize};

/// Rhai sandbox limits (`[sandbox]`). Generous defaults: a runaway loop stops after about ten
/// seconds of pure computation. Every value is a positive integer.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Sandbox {
    pub max_operations: u64,
    pub max_call_levels: usize,
    pub max_expr_depth: usize,
    pub max_string_size: usize,
    pub max_array_size: usize,
    pub max_map_size: usize,
}

impl Default for Sandbox {
    fn default() -> Self {
        Self {
            max_operations: 500_000_000,
            max_call_levels: 128,
            max_expr_depth: 256,
            max_string_size: 64 << 20,
            max_array_size: 50_000_000,
            max_map_size: 1_000_000,
        }
    }
}

impl Sandbox {
    /// Every limit positive: `Err((key, message))` names the first that is not.
    pub fn validate(&self) -> Result<(), (String, String)> {
        for (k, v) in [
            ("max_operations", self.max_operations),
            ("max_call_levels", self.max_call_levels as u64),
            ("max_expr_depth", self.max_expr_depth as u64),
            ("max_string_size", self.max_string_size as u64),
            ("max_array_size", self.max_array_size as u64),
            ("max_map_size", self.max_map_size as u64),
        ] {
            if v == 0 {
                return Err((
                    format!("sandbox.{k}"),
                    "0: must be a positive integer".into(),
                ));
            }
        }
        Ok(())
    }
}

/// `[session]`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SessionConfig {
    /// Session folder for scans, figures and `session.log` (`--data` overrides it).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub data_dir: Option<String>,
}

/// `[optics]`: the optics the session starts with, as `set_optics` would set them; a key left
/// out keeps its default ([`Optics::default`]).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct OpticsConfig {
    #[serde(skip_serializing_if = "Option::is_none")]
    pub wavelength_nm: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub n_medium: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub w0_nm: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub na: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub qpd_na: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub power_mw: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pupil_filling: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub n_theta: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub n_phi: Option<usize>,
    /// `"vector"` or `"paraxial"`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub beam: Option<String>,
}

impl OpticsConfig {
    /// True when the table sets nothing (the defaults hold).
    pub fn is_empty(&self) -> bool {
        *self == OpticsConfig::default()
    }

    /// The optics these keys give over the defaults, validated as `set_optics` validates.
    /// `Err((key, message))`: the message names the key, its value and the allowed range.
    pub fn resolve(&self) -> Result<ValidOptics, (String, String)> {
        let mut o = Optics::default();
        for (v, f) in [
            (self.wavelength_nm, &mut o.wavelength_nm as &mut f64),
            (self.n_medium, &mut o.n_medium),
            (self.w0_nm, &mut o.w0_nm),
            (self.na, &mut o.na),
            (self.qpd_na, &mut o.qpd_na),
            (self.power_mw, &mut o.power_mw),
            (self.pupil_filling, &mut o.pupil_filling),
        ] {
            if let Some(v) = v {
                *f = v;
            }
        }
        if let Some(n) = self.n_theta {
            o.n_theta = n;
        }
        if let Some(n) = self.n_phi {
            o.n_phi = n;
        }
        if let Some(b) = &self.beam {
            o.beam = Beam::parse(b).map_err(|e| ("optics.beam".to_string(), e.to_string()))?;
        }
        ValidOptics::new(o).map_err(|e| {
            let text = e.to_string();
            // the message starts with the field's name (`na = 2 is …`): point at that key
            let key = text
                .split([' ', '='])
                .next()
                .filter(|k| !k.is_empty())
                .map_or_else(|| "optics".to_string(), |k| format!("optics.{k}"));
            (key, text)
        })
    }
}
