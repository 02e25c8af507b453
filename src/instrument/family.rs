//! What a device family declares (the type; the list of families is `registry.rs`). A leaf:
//! every family's folder names its `FAMILY` with it, and the registry lists them.

use super::tables::{SectionError, Tables};
use super::{DeviceError, Instrument, Qpd, Stage};

/// The backend an instrument opened through `bfpscope.toml`'s tables reports (`status().backend`,
/// the scan metadata's `instrument.backend`), whichever families its stage and QPD are from.
pub const HARDWARE: &str = "hardware";

pub use super::tables::Backend;

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

impl Open {
    /// Through the tables, with the `[stage]` backend `stage` and the `[qpd]` backend `qpd`.
    pub const fn config(stage: &'static str, qpd: &'static str) -> Open {
        Open::Config { stage, qpd }
    }
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
    /// Its part of `bfpscope.toml`: the checks of its keys and how its devices open from
    /// the tables ([`NO_SECTION`] for a family the file cannot name).
    pub section: Section,
    /// Its part of `connect`'s help.
    pub help: ConnectHelp,
}

impl Family {
    /// A family named `name`, answering `connect` as `backend`, opened by `open`, with nothing
    /// else of its own: no aliases, devices or keys, the default stage settings, no section of
    /// `bfpscope.toml`, no help. A family's `FAMILY` names what it adds and takes the rest from
    /// here (`Family { keys: …, ..Family::new(…) }`).
    pub const fn new(name: &'static str, backend: &'static str, open: Open) -> Family {
        Family {
            name,
            backend,
            aliases: &[],
            stages: &[],
            qpds: &[],
            keys: &[],
            open,
            stage_defaults: STAGE_DEFAULTS,
            section: NO_SECTION,
            help: ConnectHelp::entry(""),
        }
    }
}

/// A family's words in `help("connect")`.
#[derive(Clone, Copy)]
pub struct ConnectHelp {
    /// Its entry in the list of backends (`"sim"`: what it is), empty for none.
    pub backend: &'static str,
    /// Its sentences in the help's text, empty for none.
    pub about: &'static str,
}

impl ConnectHelp {
    /// An entry in the backend list and no sentences of its own.
    pub const fn entry(backend: &'static str) -> ConnectHelp {
        ConnectHelp { backend, about: "" }
    }
}

/// A device opened from the tables, and its description (the scan metadata's
/// `instrument.stage` / `instrument.qpd`).
pub struct Opened<T> {
    pub device: T,
    pub description: serde_json::Value,
}

/// Why a family could not open a device from the tables: a value of the tables, or the
/// device.
#[derive(Debug)]
pub enum OpenError {
    Table(SectionError),
    Device(DeviceError),
}

impl From<SectionError> for OpenError {
    fn from(e: SectionError) -> Self {
        OpenError::Table(e)
    }
}

impl From<DeviceError> for OpenError {
    fn from(e: DeviceError) -> Self {
        OpenError::Device(e)
    }
}

/// The checks of a family's keys (called for every file, whichever backends it names: a key
/// of this family given for another's device is refused here too).
pub type ValidateFn = fn(&Tables) -> Result<(), SectionError>;
/// Open the `[stage]` the tables name (read-only: `connect` switches it on once the limits fit).
pub type OpenStageFn = fn(&Tables) -> Result<Opened<Box<dyn Stage>>, OpenError>;
/// Open the `[qpd]` the tables name.
pub type OpenQpdFn = fn(&Tables) -> Result<Opened<Box<dyn Qpd>>, OpenError>;
/// Open the stage and the QPD together when the family ties them (the NI board driving the
/// Nano-Drive's external inputs); `None` when the tables do not ask for it.
pub type OpenPairFn = fn(&Tables) -> Result<Option<OpenedPair>, OpenError>;
/// A stage and a QPD opened together.
pub type OpenedPair = (Opened<Box<dyn Stage>>, Opened<Box<dyn Qpd>>);

/// A family's part of `bfpscope.toml`.
#[derive(Clone, Copy)]
pub struct Section {
    pub validate: Option<ValidateFn>,
    pub open_stage: Option<OpenStageFn>,
    pub open_qpd: Option<OpenQpdFn>,
    pub open_pair: Option<OpenPairFn>,
}

impl Section {
    /// The section of a family providing a `[stage]` backend: its checks and its opening.
    pub const fn stage(validate: ValidateFn, open_stage: OpenStageFn) -> Section {
        Section {
            validate: Some(validate),
            open_stage: Some(open_stage),
            ..NO_SECTION
        }
    }
    /// The section of a family providing a `[qpd]` backend: its checks and its opening.
    pub const fn qpd(validate: ValidateFn, open_qpd: OpenQpdFn) -> Section {
        Section {
            validate: Some(validate),
            open_qpd: Some(open_qpd),
            ..NO_SECTION
        }
    }
}

/// The section of a family the file cannot name (`sim`, `mock`, a test's).
pub const NO_SECTION: Section = Section {
    validate: None,
    open_stage: None,
    open_qpd: None,
    open_pair: None,
};

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
