//! The instrument part of `bfpscope.toml`: backends and ports, serial settings, axis map,
//! settle time, QPD calibration, and the `[safety]` table (soft limits, step and speed limits;
//! defined and enforced by `acquire::limits`, parsed and validated here with the rest of the
//! file).
//!
//! ```toml
//! [stage]
//! backend = "gcs"               # "sim" (default) | "gcs"
//! port = "/dev/ttyUSB0"        # or "tcp://192.168.0.10:50000"; or, split across controllers:
//!                               # ports = { x = "/dev/ttyUSB0", y = "/dev/ttyUSB0", z = "/dev/ttyUSB2" }
//! baud = 115200
//! axes = { x = "1", y = "2", z = "3" }   # checked against the controller's SAI? at connect
//!
//! [qpd]
//! backend = "scpi"              # "sim" (default) | "scpi" | "kpa101" | "redpitaya"
//! port = "/dev/ttyUSB1"
//! calibration = { gain = [0.5, 0.5, 0.25], offset_v = [0.0, 0.0, 0.0] }
//! # a Red Pitaya STEMlab instead (TCP, SCPI server port 5000):
//! # backend = "redpitaya"
//! # host = "rp-f0a1b2.local"
//! # port = 5000
//! # channels = { sx = 1, sy = 2, sz = 3 }   # inputs IN1..IN4; sz only on the 4-input model
//! # sample_rate_hz = 100000.0              # nominal QPD rate: a read of n samples lasts n / rate
//! # input_gain = "LV"                      # LV ±1 V | HV ±20 V, as the jumpers are set
//!
//! [safety]                     # enforced by the scan engine for every backend
//! soft_limits = { x = [10.0, 90.0], y = [10.0, 90.0], z = [2.0, 18.0] }   # µm
//! max_step_um = 10.0            # largest pixel pitch of a scan, µm
//! max_speed_um_s = 500.0        # fastest a scan may move the stage, µm/s
//! ```
//!
//! With no file, everything is simulated. This module owns the whole file: besides the
//! tables above, `[sandbox]`, `[session]` and `[optics]` ([`tables`]). An unknown table or key,
//! anywhere, is an error naming the file, the key path (`stage.baud`), the line and the nearest
//! known name: a misspelled `[saftey]` must not drop the soft limits silently, nor a `[Stage]`
//! start the simulator in place of the hardware it names. The legacy `[limits]` table and
//! `stage.max_speed_um_s` are refused with their `[safety]` equivalent.

pub mod bench;
pub mod connect;
pub mod tables;

pub use tables::{OpticsConfig, Sandbox, SessionConfig};

pub use crate::instrument::tables::{
    AxisMap, AxisPorts, Backend, QpdChannels, QpdConfig, RasterConfig, StageConfig, Xy, AXIS_NAMES,
};

use crate::acquire::limits::{SafetyConfig, SoftLimits};
use crate::instrument::sim::SIM;
use crate::instrument::tables::{SectionError, Tables};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// The config file looked for in the working directory.
pub const DEFAULT_FILE: &str = "bfpscope.toml";
/// Environment variable naming a config file (takes precedence over `./bfpscope.toml`).
pub const ENV_VAR: &str = "BFPSCOPE_CONFIG";

/// Longest reply timeout a device may be given, ms (one hour): `[stage]`/`[qpd]` `timeout_ms`
/// and `connect(#{timeout_ms})`.
pub const MAX_TIMEOUT_MS: u64 = 3_600_000;

/// Highest serial baud rate `connect(#{baud, stage_baud, qpd_baud})` accepts.
pub const MAX_BAUD: u32 = 4_000_000;

/// A config problem: where (file, key path, line) and what.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{origin}: {key}: {message}{}", line.map(|l| format!(" (line {l})")).unwrap_or_default())]
pub struct ConfigError {
    /// The file (or `"<string>"`, `"defaults"`).
    pub origin: String,
    /// Dotted key path, e.g. `stage.baud` (empty for the whole file).
    pub key: String,
    /// 1-based line in the file, when known.
    pub line: Option<usize>,
    pub message: String,
}

impl StageConfig {
    /// The defaults of the family providing this stage (`instrument::registry`).
    pub fn family_defaults(&self) -> crate::instrument::registry::StageDefaults {
        crate::instrument::registry::by_stage(self.backend.as_str())
            .map_or(crate::instrument::registry::STAGE_DEFAULTS, |f| {
                f.stage_defaults
            })
    }

    /// The motion polling interval in force, ms: `poll_ms` when set, else the default of
    /// the stage's family (`Family::stage_defaults`: gcs 1, kpz101 10, madlib 0, else 5).
    pub fn poll_ms(&self) -> u64 {
        self.poll_ms.unwrap_or(self.family_defaults().poll_ms)
    }
}

/// The whole `bfpscope.toml`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    #[serde(default)]
    pub stage: StageConfig,
    #[serde(default)]
    pub qpd: QpdConfig,
    /// `[safety]`: soft limits, step and speed limits (`acquire::limits`).
    #[serde(default)]
    pub safety: SafetyConfig,
    /// `[raster]`: the NI board's hardware-timed raster (`instrument/nidaqmx/config.rs`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub raster: Option<RasterConfig>,
    /// `[sandbox]`: the script's limits.
    #[serde(default)]
    pub sandbox: Sandbox,
    /// `[session]`: where scans go.
    #[serde(default)]
    pub session: SessionConfig,
    /// `[optics]`: the optics the session starts with.
    #[serde(default, skip_serializing_if = "OpticsConfig::is_empty")]
    pub optics: OpticsConfig,
}

/// The top-level tables of `bfpscope.toml`.
pub const TABLES: [&str; 7] = [
    "stage", "qpd", "safety", "sandbox", "session", "optics", "raster",
];

/// The key path and 1-based line at byte `offset` of a TOML text, by tracking `[table]`
/// headers and `key =` lines (good enough for error messages).
fn key_path_at(src: &str, offset: usize) -> (String, usize) {
    let mut table = String::new();
    let mut key = String::new();
    let mut start = 0usize;
    for (n, line) in src.split_inclusive('\n').enumerate() {
        let t = line.trim();
        if let Some(header) = table_header(t) {
            table = header;
            key.clear();
        } else if let Some((k, _)) = t.split_once('=') {
            if !t.starts_with('#') {
                key = k.trim().trim_matches('"').to_string();
            }
        }
        let end = start + line.len();
        if offset < end || end == src.len() {
            let path = match (table.is_empty(), key.is_empty()) {
                (_, true) => table.clone(),
                (true, false) => key.clone(),
                (false, false) => format!("{table}.{key}"),
            };
            return (path, n + 1);
        }
        start = end;
    }
    (String::new(), 1)
}

/// `[a.b]` / `[[a.b]]` → `a.b`; None for other lines (including arrays such as `[1, 2],`).
fn table_header(line: &str) -> Option<String> {
    let inner = line.strip_prefix('[')?;
    let inner = inner.strip_prefix('[').unwrap_or(inner);
    let (inner, rest) = inner.split_once(']')?;
    let rest = rest.trim_start_matches(']').trim();
    if !(rest.is_empty() || rest.starts_with('#')) {
        return None;
    }
    let inner = inner.trim();
    let first = inner.chars().next()?;
    let ok = !first.is_ascii_digit()
        && first != '-'
        && inner
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "_-.\" ".contains(c));
    ok.then(|| {
        inner
            .split('.')
            .map(|s| s.trim().trim_matches('"'))
            .collect::<Vec<_>>()
            .join(".")
    })
}

/// A family's complaint about its section, as the config's (the file and line come later).
fn section_error(e: SectionError) -> ConfigError {
    err(&e.key, e.message)
}

fn err(key: &str, message: impl Into<String>) -> ConfigError {
    ConfigError {
        origin: String::new(),
        key: key.into(),
        line: None,
        message: message.into(),
    }
}

/// serde's `unknown field `saftey`, expected one of `stage`, …` with the nearest known name
/// first: `unknown field `saftey`; did you mean `safety`? (known: `stage`, …)`. Nearest: within
/// two edits (a third of the word's length for long words), or a known name the word begins
/// (`max_step` → `max_step_um`); words under three letters get no guess. Without a guess, and
/// for other messages, serde's text is returned unchanged.
fn with_nearest(message: &str) -> String {
    let Some(rest) = message.strip_prefix("unknown field `") else {
        return message.to_string();
    };
    let Some((word, tail)) = rest.split_once('`') else {
        return message.to_string();
    };
    let known: Vec<&str> = tail.split('`').skip(1).step_by(2).collect();
    let w = word.to_lowercase();
    let limit = (w.chars().count() / 3).max(2);
    let nearest = known
        .iter()
        .filter_map(|k| {
            let kl = k.to_lowercase();
            let d = strsim::damerau_levenshtein(&w, &kl);
            if d <= limit {
                Some((d, *k))
            } else if kl.starts_with(&w) {
                Some((limit + 1, *k))
            } else {
                None
            }
        })
        .min()
        .filter(|_| w.chars().count() >= 3);
    match nearest {
        Some((_, k)) => {
            let list = known
                .iter()
                .map(|k| format!("`{k}`"))
                .collect::<Vec<_>>()
                .join(", ");
            format!("unknown field `{word}`; did you mean `{k}`? (known: {list})")
        }
        None => message.to_string(),
    }
}

impl Config {
    /// Parse and validate TOML text. `origin` names the text in messages (a file path).
    pub fn from_toml_str(text: &str, origin: &str) -> Result<Config, ConfigError> {
        // `[stage] max_speed_um_s` moved to `[safety]`: say so rather than "unknown field".
        if let Ok(raw) = toml::from_str::<toml::Table>(text) {
            if let Some(old) = raw.get("limits") {
                return Err(ConfigError {
                    origin: origin.into(),
                    key: "limits".into(),
                    line: find_table_line(text, "limits").or_else(|| find_key_line(text, "limits")),
                    message: legacy_limits_message(old),
                });
            }
            if let Some(v) = raw.get("stage").and_then(|s| s.get("max_speed_um_s")) {
                return Err(ConfigError {
                    origin: origin.into(),
                    key: "stage.max_speed_um_s".into(),
                    line: find_key_line(text, "stage.max_speed_um_s"),
                    message: format!(
                        "moved to [safety]: write `max_speed_um_s = {v}` in [safety] (enforced by the scan engine \
                         for every backend)"
                    ),
                });
            }
        }
        let mut cfg: Config = toml::from_str(text).map_err(|e| {
            let (key, line) = match e.span() {
                Some(span) => {
                    let (k, l) = key_path_at(text, span.start);
                    (k, Some(l))
                }
                None => (String::new(), None),
            };
            ConfigError {
                origin: origin.into(),
                key,
                line,
                message: with_nearest(e.message().trim()),
            }
        })?;
        // A family's own settle time (a Nano-Drive is settled on its readings: none after
        // them) unless the file asks for one.
        let settle_given = toml::from_str::<toml::Table>(text)
            .ok()
            .is_some_and(|r| r.get("stage").and_then(|s| s.get("settle_s")).is_some());
        if let (Some(s), false) = (cfg.stage.family_defaults().settle_s, settle_given) {
            cfg.stage.settle_s = s;
        }
        cfg.validate().map_err(|mut e| {
            e.origin = origin.into();
            e.line = find_key_line(text, &e.key).or_else(|| find_table_line(text, &e.key));
            e
        })?;
        Ok(cfg)
    }

    /// Read, parse and validate a config file.
    pub fn load(path: &Path) -> Result<Config, ConfigError> {
        let origin = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|e| ConfigError {
            origin: origin.clone(),
            key: String::new(),
            line: None,
            message: format!("cannot read: {e}"),
        })?;
        Self::from_toml_str(&text, &origin)
    }

    /// TOML text of this config.
    pub fn to_toml(&self) -> String {
        toml::to_string_pretty(self).unwrap_or_else(|e| format!("# cannot serialise config: {e}\n"))
    }

    /// True when both devices are simulated.
    pub fn is_simulated(&self) -> bool {
        self.stage.backend == SIM && self.qpd.backend == SIM
    }

    /// Check values and combinations. Errors name the key path.
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.validate_backends()?;
        self.validate_devices()?;
        self.validate_links()?;
        self.validate_axes()?;
        self.validate_stage_numbers()?;
        self.validate_qpd_numbers()?;
        self.safety.validate().map_err(|(k, m)| err(&k, m))?;
        self.sandbox.validate().map_err(|(k, m)| err(&k, m))?;
        self.optics.resolve().map_err(|(k, m)| err(&k, m))?;
        if let Some(d) = &self.session.data_dir {
            if d.trim().is_empty() {
                return Err(err(
                    "session.data_dir",
                    "\"\": must name a folder (or leave the key out for ./bfpscope_data/YYYY-MM-DD/)",
                ));
            }
        }
        Ok(())
    }

    /// The `[stage]` and `[qpd]` backends: each the kind its family provides, both simulated or both hardware.
    fn validate_backends(&self) -> Result<(), ConfigError> {
        let s = &self.stage;
        let q = &self.qpd;
        // which backend is a stage's and which a QPD's: the device families say
        for (key, b, qpd, other) in [
            ("stage.backend", s.backend, false, "QPD"),
            ("qpd.backend", q.backend, true, "stage"),
        ] {
            let allowed = crate::instrument::registry::config_backends(qpd);
            if !allowed.contains(&b.as_str()) {
                let listed: Vec<String> = allowed.iter().map(|b| format!("{b:?}")).collect();
                return Err(err(
                    key,
                    format!(
                        "\"{}\" is a {other} backend; allowed for a {}: {}",
                        b.as_str(),
                        if qpd { "QPD" } else { "stage" },
                        listed.join(", ")
                    ),
                ));
            }
        }
        if (s.backend == SIM) != (q.backend == SIM) {
            return Err(err(
                "qpd.backend",
                format!(
                    "stage is \"{}\" but qpd is \"{}\": use both simulated or both hardware (the simulated QPD \
                     images the simulated stage's scene)",
                    s.backend.as_str(),
                    q.backend.as_str()
                ),
            ));
        }
        Ok(())
    }

    /// The rules of each device family (`instrument::registry`: its `Section`), the stage's
    /// family first, then the QPD's, then the others (which refuse their keys given for
    /// another family's device); then one port per device.
    fn validate_devices(&self) -> Result<(), ConfigError> {
        let tables = self.tables();
        let mut families = crate::instrument::registry::families();
        let rank = |f: &crate::instrument::registry::Family| {
            if f.stages.contains(&self.stage.backend.as_str()) {
                0
            } else if f.qpds.contains(&self.qpd.backend.as_str()) {
                1
            } else {
                2
            }
        };
        families.sort_by_key(rank);
        for f in families {
            if let Some(check) = f.section.validate {
                check(&tables).map_err(section_error)?;
            }
        }
        let q = &self.qpd;
        // a QPD on a network host has a TCP port number there, not a device path
        if q.backend != SIM && q.host.is_none() {
            if let Some(qp) = &q.port {
                if self.stage.distinct_ports().iter().any(|p| p == qp) {
                    return Err(err(
                        "qpd.port",
                        format!("{qp:?}: the stage and the QPD cannot share one port"),
                    ));
                }
            }
        }
        Ok(())
    }

    /// The `[stage]`, `[qpd]` and `[raster]` tables, as the device families read them.
    pub fn tables(&self) -> Tables<'_> {
        Tables {
            stage: &self.stage,
            qpd: &self.qpd,
            raster: self.raster.as_ref(),
        }
    }

    /// Baud rates and timeouts.
    fn validate_links(&self) -> Result<(), ConfigError> {
        let s = &self.stage;
        let q = &self.qpd;
        for (key, v) in [("stage.baud", s.baud), ("qpd.baud", q.baud)] {
            if v == 0 {
                return Err(err(key, "must be a positive baud rate (e.g. 115200)"));
            }
        }
        for (key, v) in [
            ("stage.timeout_ms", s.timeout_ms),
            ("stage.on_target_timeout_ms", s.on_target_timeout_ms),
            // a value given must be ≥ 1 ms; a backend's default may be 0 (Madlib: back to back)
            ("stage.poll_ms", s.poll_ms.unwrap_or(1)),
            ("stage.zero_timeout_ms", s.zero_timeout_ms),
            ("qpd.timeout_ms", q.timeout_ms),
        ] {
            if v == 0 || v > MAX_TIMEOUT_MS {
                return Err(err(
                    key,
                    format!("{v} ms: must be between 1 ms and one hour"),
                ));
            }
        }
        Ok(())
    }

    /// `stage.axes`: controller axis identifiers, different on one controller.
    fn validate_axes(&self) -> Result<(), ConfigError> {
        let s = &self.stage;
        let axes = [&s.axes.x, &s.axes.y, &s.axes.z];
        for (i, a) in axes.iter().enumerate() {
            if a.is_empty() || a.contains(char::is_whitespace) || a.contains('=') {
                return Err(err(
                    &format!("stage.axes.{}", AXIS_NAMES[i]),
                    format!("{a:?} is not a controller axis identifier"),
                ));
            }
        }
        // axes on one controller (one port) must differ
        let port_of = |i: usize| match &s.ports {
            Some(p) => p.get(i).to_string(),
            None => s.port.clone().unwrap_or_default(),
        };
        for i in 0..3 {
            for j in i + 1..3 {
                if axes[i] == axes[j] && port_of(i) == port_of(j) {
                    return Err(err(
                        "stage.axes",
                        format!(
                            "{} and {} are both {:?} on one controller: x, y and z must be different \
                             controller axes (the identifiers `SAI?` lists)",
                            AXIS_NAMES[i], AXIS_NAMES[j], axes[i]
                        ),
                    ));
                }
            }
        }
        Ok(())
    }

    /// The stage's numbers: units, settle time, trigger line, servo cycle, table sizes.
    fn validate_stage_numbers(&self) -> Result<(), ConfigError> {
        let s = &self.stage;
        if !(s.units_per_um.is_finite() && s.units_per_um > 0.0) {
            return Err(err("stage.units_per_um", "must be a positive number"));
        }
        if !(s.settle_s.is_finite() && (0.0..=60.0).contains(&s.settle_s)) {
            return Err(err("stage.settle_s", "must be between 0 and 60 s"));
        }
        if let Some(l) = s.trigger_line {
            if !(1..=3).contains(&l) {
                return Err(err(
                    "stage.trigger_line",
                    format!(
                        "{l}: the controller's digital output wired to the digitiser's trigger, 1, 2 or 3 (OUT1…OUT3, `CTO`)"
                    ),
                ));
            }
        }
        if let Some(c) = s.servo_cycle_s {
            if !(c.is_finite() && c > 0.0 && c <= 0.1) {
                return Err(err(
                    "stage.servo_cycle_s",
                    format!("{c}: the servo cycle must be between 0 and 0.1 s (E-727: 50e-6)"),
                ));
            }
        }
        for (key, v) in [
            ("stage.max_wave_points", s.max_wave_points),
            ("stage.max_record_points", s.max_record_points),
        ] {
            if v == Some(0) {
                return Err(err(key, "0: must be a positive number of points"));
            }
        }
        Ok(())
    }

    /// The QPD's numbers: calibration, sum floor, input range.
    fn validate_qpd_numbers(&self) -> Result<(), ConfigError> {
        let q = &self.qpd;
        for i in 0..3 {
            let g = q.calibration.gain[i];
            if !(g.is_finite() && g != 0.0) {
                return Err(err(
                    "qpd.calibration.gain",
                    format!("channel {i}: {g} must be finite and nonzero"),
                ));
            }
            if !q.calibration.offset_v[i].is_finite() {
                return Err(err("qpd.calibration.offset_v", "must be finite"));
            }
        }
        if let Some(f) = q.sum_floor {
            if q.backend == SIM {
                return Err(err(
                    "qpd.sum_floor",
                    format!("{f}: the simulated QPD has no sum input to check; a scene's `detector_range` effect sets the simulator's floor (`sum_floor`)"),
                ));
            }
            if !(f.is_finite() && f >= 0.0) {
                return Err(err(
                    "qpd.sum_floor",
                    format!("{f}: the sum input's floor in V, 0 (no check) or above"),
                ));
            }
        }
        Ok(())
    }

    /// The safety rules in force before narrowing to a stage's travel range.
    pub fn soft_limits(&self) -> SoftLimits {
        self.safety.limits()
    }
}

/// The message for a legacy `[limits]` table: its `[safety]` equivalent, spelled out.
fn legacy_limits_message(old: &toml::Value) -> String {
    let mut axes = vec![];
    let mut rest = vec![];
    if let Some(t) = old.as_table() {
        for (k, v) in t {
            match k.as_str() {
                "x" | "y" | "z" => axes.push(format!("{k} = {v}")),
                _ => rest.push(format!("{k} = {v}")),
            }
        }
    }
    let mut s = String::from("the [limits] table is now [safety] (same meanings; max_step_um is the largest pixel pitch of a scan): write [safety]");
    if !axes.is_empty() {
        s.push_str(&format!(" soft_limits = {{ {} }}", axes.join(", ")));
    }
    for r in rest {
        s.push_str(&format!(", {r}"));
    }
    s
}

/// Line of the `[table]` header for `key` (validation errors about a whole table).
fn find_table_line(text: &str, key: &str) -> Option<usize> {
    text.lines()
        .position(|l| table_header(l.trim()).as_deref() == Some(key))
        .map(|n| n + 1)
}

/// Line where `key` (a dotted path) is set, for validation errors: a `k = …` line whose
/// table path plus `k` is `key` or a prefix of it (inline tables such as `axes = { x = … }`).
fn find_key_line(text: &str, key: &str) -> Option<usize> {
    if key.is_empty() {
        return None;
    }
    let mut table = String::new();
    for (n, line) in text.lines().enumerate() {
        let t = line.trim();
        if let Some(h) = table_header(t) {
            table = h;
            continue;
        }
        if t.starts_with('#') {
            continue;
        }
        if let Some((k, _)) = t.split_once('=') {
            let k = k.trim().trim_matches('"');
            let path = if table.is_empty() {
                k.to_string()
            } else {
                format!("{table}.{k}")
            };
            if key == path || key.starts_with(&format!("{path}.")) {
                return Some(n + 1);
            }
        }
    }
    None
}

#[cfg(test)]
mod tests;
