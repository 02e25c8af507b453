//! What a device family declares (the type; the list of families is `registry.rs`). A leaf:
//! every family's folder names its `FAMILY` with it, and the registry lists them.

use super::Instrument;

/// The backend an instrument opened through `bfpscope.toml`'s tables reports (`status().backend`,
/// the scan metadata's `instrument.backend`), whichever families its stage and QPD are from.
pub const HARDWARE: &str = "hardware";

/// A `[stage]` or `[qpd]` backend of `bfpscope.toml`: a name some family provides
/// ([`Family::stages`], [`Family::qpds`]); each family's folder names its own (`gcs::GCS`).
/// Read from the file through the registry (`registry::config_backend`): a name no family
/// provides is refused, listing those that are.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Backend(pub &'static str);

impl Backend {
    /// The name written in `bfpscope.toml`.
    pub fn as_str(self) -> &'static str {
        self.0
    }
}

impl serde::Serialize for Backend {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.0)
    }
}

/// How `connect` opens a family.
#[derive(Clone, Copy)]
pub enum Open {
    /// The simulated instrument imaging the session's scene (`sim/`).
    Sim,
    /// The mock instrument of the tests and examples (`mock/`).
    Mock,
    /// The family emulators on pseudo-terminals, connected through the real drivers
    /// (`emulator/`).
    Emulated,
    /// Through `bfpscope.toml`'s `[stage]` and `[qpd]` tables with these backends (unless
    /// `connect()` keeps the config's own): the serial, TCP and vendor-library drivers.
    Config {
        stage: &'static str,
        qpd: &'static str,
    },
    /// A function building the instrument from `connect`'s options (JSON) and the settle time.
    Build(BuildFn),
}

/// A family's own opening: `connect`'s options (every key but `backend` and `settle`, as
/// JSON) and the settle time in s → the instrument, or an error naming the device.
pub type BuildFn =
    fn(&serde_json::Map<String, serde_json::Value>, f64) -> Result<Instrument, String>;

/// One device family.
#[derive(Clone, Copy)]
pub struct Family {
    /// The folder under `src/instrument/` (and a `connect` backend name).
    pub name: &'static str,
    /// The `connect` backend it answers to in messages; families with one name share it
    /// (`"hardware"`: the PI stage with a SCPI or Red Pitaya digitiser).
    pub backend: &'static str,
    /// Other `connect` backend names that select this family (its devices: `"kpz101"`).
    pub aliases: &'static [&'static str],
    /// `[stage] backend` values of `bfpscope.toml` it provides.
    pub stages: &'static [&'static str],
    /// `[qpd] backend` values it provides.
    pub qpds: &'static [&'static str],
    /// The `connect(#{…})` keys it takes beyond `backend` and `settle`.
    pub keys: &'static [&'static str],
    /// How `connect` opens it.
    pub open: Open,
    /// What its `[stage]` takes when the file leaves a key out.
    pub stage_defaults: StageDefaults,
}

/// A family's defaults for `[stage]` keys whose best value depends on the controller.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StageDefaults {
    /// `stage.poll_ms`: the interval between motion polls after a move, ms.
    pub poll_ms: u64,
    /// `stage.settle_s`, when the family's differs from the config's (5 ms): the extra
    /// settle time after each move, s.
    pub settle_s: Option<f64>,
}

/// The defaults of a family with nothing of its own to say: polls every 5 ms, the config's
/// settle time.
pub const STAGE_DEFAULTS: StageDefaults = StageDefaults {
    poll_ms: 5,
    settle_s: None,
};
