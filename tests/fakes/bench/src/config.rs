//! The fake bench's settings: from `FAKEBENCH_*` environment variables when the library is
//! first used, or from [`crate::control`]'s `fakebench_set` / `fakebench_reset` in a test.
//!
//! | key (env: `FAKEBENCH_` + upper case) | default | meaning |
//! |---|---|---|
//! | `serial` | 2847 | the Nano-Drive's serial number |
//! | `range_um` | `75,75,50` | calibrated range per axis, µm (`MCL_GetCalibration`) |
//! | `tau_ms` | 2 | the stage's first-order lag (sensor follows target), ms |
//! | `usb_ms` | 0 | the USB round trip of one `MCL_SingleReadN` / `MCL_SingleWriteN` (a Nano-Drive: ≈ 0.2), ms |
//! | `sensor_noise_um` | 0.001 | rms noise of a sensor reading (`MCL_SingleReadN`, monitor), µm |
//! | `ext_mode` | `sum` | how the external input and the USB command combine: `sum` (the external input's position added to the USB command, as MCL documents the Nano-Drive's external input) or `replace` (whichever changed last wins; alias `override`) |
//! | `daq_device` | `Dev1` | the PCI-6120's device name |
//! | `daq_serial` | 0x01A2B3C4 | its serial number (`DAQmxGetDevSerialNum`) |
//! | `wiring` | `ai0=sx,ai1=sy,ai2=sum,ai3=x_monitor,ao0=x,ao1=y` | what each AI sees and which axis' external input each AO drives |
//! | `qpd_gain_v` | 1 | QPD amplifier: volts per signal unit for Sx, Sy |
//! | `sum_v` | 5 | the sum channel with no sample, V (sum = sum_v · (1 + Sz)) |
//! | `detector_noise_v` | 0.0005 | rms noise per AI sample, V (seeded) |
//! | `seed` | 1 | seed of every noise source |
//! | `scene` | (one 110 nm polystyrene bead) | a scene file, the format of `bfpscope emulate --scene` |
//! | `scene_origin_um` | middle of the range | stage position (µm) at which the scene's origin is under the focus |
//! | `log` | (none) | append every call to this file as well |
//! | `faults` | (none) | fault switches, see [`Faults::parse`] |

use std::path::PathBuf;

/// What an AI channel is wired to.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum AiSource {
    /// QPD difference signal Sx (volts = qpd_gain_v · Sx).
    Sx,
    /// QPD difference signal Sy.
    Sy,
    /// QPD sum (volts = sum_v · (1 + Sz)).
    Sum,
    /// The Nano-Drive's sensor monitor of an axis (0–10 V over the calibrated range).
    Monitor(usize),
    /// Nothing connected (reads noise around 0 V).
    Open,
}

/// Fault switches (not vendor behaviour; see [`Faults::parse`]).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Faults {
    /// No Nano-Drive attached: `MCL_InitHandle` returns 0, `MCL_GrabAllHandles` 0.
    pub no_stage: bool,
    /// The Nano-Drive is unplugged after this many more Madlib calls that name a handle:
    /// `MCL_DEV_NOT_ATTACHED` from then on.
    pub stage_unplug_after: Option<u64>,
    /// Axes (0 = x) whose piezo is stuck: the sensor stays where it was, never reaching a
    /// new target.
    pub stage_stuck: [bool; 3],
    /// The DAQ device is not in the system: every channel on it gets −200220.
    pub daq_missing: bool,
    /// The DAQ device is removed after this many more `DAQmxRead*` calls: −201003 from then on.
    pub daq_removed_after_reads: Option<u64>,
    /// The sample clock never ticks (a trigger that never comes): reads time out (−200284).
    pub read_timeout: bool,
    /// A continuous AI stream overflows after this many more reads: the next read
    /// returns −200279 (as if the reader had fallen behind by more than the buffer).
    pub overflow_after_reads: Option<u64>,
}

impl Faults {
    /// Parse `item,item,…` where an item is `no_stage`, `stage_unplug_after=N`,
    /// `stage_stuck` (all axes) or `stage_stuck=x|y|z`, `daq_missing`,
    /// `daq_removed_after_reads=N`, `read_timeout`, `overflow_after_reads=N`; `none` or an
    /// empty string: no faults.
    pub fn parse(s: &str) -> Result<Faults, String> {
        let mut f = Faults::default();
        for item in s.split(',').map(str::trim).filter(|i| !i.is_empty()) {
            let (k, v) = match item.split_once('=') {
                Some((k, v)) => (k.trim(), Some(v.trim())),
                None => (item, None),
            };
            let n = |v: Option<&str>| -> Result<u64, String> {
                v.and_then(|v| v.parse::<u64>().ok()).ok_or_else(|| {
                    format!(
                        "fault `{item}`: `{k}` needs a count, e.g. `{k}=3` (a whole number ≥ 0)"
                    )
                })
            };
            match k {
                "none" => {}
                "no_stage" => f.no_stage = true,
                "stage_unplug_after" => f.stage_unplug_after = Some(n(v)?),
                "stage_stuck" => match v {
                    None => f.stage_stuck = [true; 3],
                    Some(a) => {
                        let i = axis_index(a).ok_or_else(|| {
                            format!("fault `{item}`: axis `{a}`: allowed are x, y, z")
                        })?;
                        f.stage_stuck[i] = true;
                    }
                },
                "daq_missing" => f.daq_missing = true,
                "daq_removed_after_reads" => f.daq_removed_after_reads = Some(n(v)?),
                "read_timeout" => f.read_timeout = true,
                "overflow_after_reads" => f.overflow_after_reads = Some(n(v)?),
                _ => {
                    return Err(format!(
                        "fault `{item}`: unknown; allowed are no_stage, stage_unplug_after=N, stage_stuck[=x|y|z], \
                         daq_missing, daq_removed_after_reads=N, read_timeout, overflow_after_reads=N"
                    ))
                }
            }
        }
        Ok(f)
    }
}

fn axis_index(a: &str) -> Option<usize> {
    match a {
        "x" | "X" | "1" => Some(0),
        "y" | "Y" | "2" => Some(1),
        "z" | "Z" | "3" => Some(2),
        _ => None,
    }
}

/// The bench's settings (see the module documentation).
#[derive(Debug, Clone, PartialEq)]
pub struct Config {
    pub serial: i32,
    pub range_um: [f64; 3],
    pub tau_s: f64,
    /// The USB round trip of one `MCL_SingleReadN` / `MCL_SingleWriteN`, s (`usb_ms`;
    /// default 0; MCL's Nano-Drives: about 0.2 ms).
    pub usb_s: f64,
    pub sensor_noise_um: f64,
    pub ext_sum: bool,
    pub daq_device: String,
    pub daq_serial: u32,
    /// AI channel i is wired to `ai[i]`.
    pub ai: [AiSource; 4],
    /// AO channel i drives the external input of axis `ao[i]` (None: not connected).
    pub ao: [Option<usize>; 2],
    pub qpd_gain_v: f64,
    pub sum_v: f64,
    pub detector_noise_v: f64,
    pub seed: u64,
    pub scene: Option<PathBuf>,
    pub scene_origin_um: Option<[f64; 3]>,
    pub log_path: Option<PathBuf>,
    pub faults: Faults,
    /// Settings that could not be read (each names its key, value and what is allowed); the
    /// default was kept.
    pub errors: Vec<String>,
}

impl Default for Config {
    fn default() -> Self {
        Config {
            serial: 2847,
            range_um: [75.0, 75.0, 50.0],
            tau_s: 0.002,
            usb_s: 0.0,
            sensor_noise_um: 0.001,
            ext_sum: true,
            daq_device: "Dev1".into(),
            daq_serial: 0x01A2_B3C4,
            ai: [
                AiSource::Sx,
                AiSource::Sy,
                AiSource::Sum,
                AiSource::Monitor(0),
            ],
            ao: [Some(0), Some(1)],
            qpd_gain_v: 1.0,
            sum_v: 5.0,
            detector_noise_v: 0.0005,
            seed: 1,
            scene: None,
            scene_origin_um: None,
            log_path: None,
            faults: Faults::default(),
            errors: Vec::new(),
        }
    }
}

/// Every key `set` accepts.
pub const KEYS: [&str; 18] = [
    "serial",
    "range_um",
    "tau_ms",
    "usb_ms",
    "sensor_noise_um",
    "ext_mode",
    "daq_device",
    "daq_serial",
    "wiring",
    "qpd_gain_v",
    "sum_v",
    "detector_noise_v",
    "seed",
    "scene",
    "scene_origin_um",
    "log",
    "faults",
    "range",
];

fn num(key: &str, v: &str, lo: f64, hi: f64, unit: &str) -> Result<f64, String> {
    match v.trim().parse::<f64>() {
        Ok(x) if x.is_finite() && (lo..=hi).contains(&x) => Ok(x),
        _ => Err(format!(
            "{key} = `{v}`: allowed is a number in {lo}–{hi} {unit}"
        )),
    }
}

fn triple(key: &str, v: &str, lo: f64, hi: f64) -> Result<[f64; 3], String> {
    let parts: Vec<&str> = v.split(',').map(str::trim).collect();
    if parts.len() != 3 {
        return Err(format!(
            "{key} = `{v}`: allowed are three numbers `x,y,z` in {lo}–{hi} µm"
        ));
    }
    let mut out = [0.0; 3];
    for (o, p) in out.iter_mut().zip(&parts) {
        *o = num(key, p, lo, hi, "µm")?;
    }
    Ok(out)
}

impl Config {
    /// The settings from the `FAKEBENCH_*` environment variables (unreadable ones keep their
    /// default, are printed on stderr and listed in [`Config::errors`]).
    pub fn from_env() -> Config {
        let mut c = Config::default();
        for key in KEYS {
            let var = format!("FAKEBENCH_{}", key.to_uppercase());
            if let Ok(v) = std::env::var(&var) {
                if let Err(e) = c.set(key, &v) {
                    let msg = format!("{var}: {e}");
                    eprintln!("fakebench: {msg} (kept the default)");
                    c.errors.push(msg);
                }
            }
        }
        c
    }

    /// Change one setting (`key` as in the module's table).
    pub fn set(&mut self, key: &str, v: &str) -> Result<(), String> {
        match key {
            "serial" => {
                self.serial = v
                    .trim()
                    .parse::<i32>()
                    .ok()
                    .filter(|s| (1..=32767).contains(s))
                    .ok_or_else(|| {
                        format!("serial = `{v}`: allowed is a whole number in 1–32767 (Madlib passes serials as short)")
                    })?
            }
            "range_um" | "range" => {
                let r = triple(key, v, 1.0, 1000.0)?;
                self.range_um = r;
            }
            "tau_ms" => self.tau_s = num(key, v, 0.0, 1000.0, "ms")? / 1e3,
            "usb_ms" => self.usb_s = num(key, v, 0.0, 100.0, "ms")? / 1e3,
            "sensor_noise_um" => self.sensor_noise_um = num(key, v, 0.0, 10.0, "µm")?,
            "ext_mode" => {
                self.ext_sum = match v.trim() {
                    "replace" | "override" => false,
                    "sum" => true,
                    _ => {
                        return Err(format!(
                            "ext_mode = `{v}`: allowed are `sum` and `replace` (alias `override`)"
                        ))
                    }
                }
            }
            "daq_device" => {
                let d = v.trim();
                if d.is_empty() || d.contains('/') || d.contains(',') {
                    return Err(format!(
                        "daq_device = `{v}`: allowed is a device name such as Dev1 (no `/` or `,`)"
                    ));
                }
                self.daq_device = d.to_string();
            }
            "daq_serial" => {
                self.daq_serial = v.trim().parse::<u32>().map_err(|_| {
                    format!("daq_serial = `{v}`: allowed is a whole number in 0–4294967295")
                })?
            }
            "wiring" => self.set_wiring(v)?,
            "qpd_gain_v" => self.qpd_gain_v = num(key, v, 0.0, 1000.0, "V per signal unit")?,
            "sum_v" => self.sum_v = num(key, v, 0.0, 42.0, "V")?,
            "detector_noise_v" => self.detector_noise_v = num(key, v, 0.0, 10.0, "V")?,
            "seed" => {
                self.seed = v
                    .trim()
                    .parse::<u64>()
                    .map_err(|_| format!("seed = `{v}`: allowed is a whole number ≥ 0"))?
            }
            "scene" => {
                self.scene = if v.trim().is_empty() {
                    None
                } else {
                    Some(PathBuf::from(v.trim()))
                }
            }
            "scene_origin_um" => self.scene_origin_um = Some(triple(key, v, -1000.0, 1000.0)?),
            "log" => {
                self.log_path = if v.trim().is_empty() {
                    None
                } else {
                    Some(PathBuf::from(v.trim()))
                }
            }
            "faults" => self.faults = Faults::parse(v)?,
            _ => {
                return Err(format!(
                    "unknown setting `{key}`; allowed are {}",
                    KEYS[..17].join(", ")
                ))
            }
        }
        Ok(())
    }

    fn set_wiring(&mut self, v: &str) -> Result<(), String> {
        let mut ai = self.ai;
        let mut ao = self.ao;
        for item in v.split(',').map(str::trim).filter(|i| !i.is_empty()) {
            let bad = || {
                format!(
                    "wiring item `{item}`: allowed are ai0–ai3 = sx|sy|sum|x_monitor|y_monitor|z_monitor|open \
                     and ao0–ao1 = x|y|z|open"
                )
            };
            let (ch, what) = item.split_once('=').ok_or_else(bad)?;
            let (ch, what) = (ch.trim(), what.trim());
            if let Some(i) = ch.strip_prefix("ai").and_then(|i| i.parse::<usize>().ok()) {
                if i >= 4 {
                    return Err(bad());
                }
                ai[i] = match what {
                    "sx" => AiSource::Sx,
                    "sy" => AiSource::Sy,
                    "sum" => AiSource::Sum,
                    "open" => AiSource::Open,
                    m => match m.strip_suffix("_monitor").and_then(axis_index) {
                        Some(a) => AiSource::Monitor(a),
                        None => return Err(bad()),
                    },
                };
            } else if let Some(i) = ch.strip_prefix("ao").and_then(|i| i.parse::<usize>().ok()) {
                if i >= 2 {
                    return Err(bad());
                }
                ao[i] = match what {
                    "open" => None,
                    a => Some(axis_index(a).ok_or_else(bad)?),
                };
            } else {
                return Err(bad());
            }
        }
        self.ai = ai;
        self.ao = ao;
        Ok(())
    }

    /// Stage position (µm) at which the scene's origin is under the focus: the setting, else
    /// the middle of the calibrated range.
    pub fn origin(&self) -> [f64; 3] {
        self.scene_origin_um.unwrap_or([
            self.range_um[0] / 2.0,
            self.range_um[1] / 2.0,
            self.range_um[2] / 2.0,
        ])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn faults_parse_and_refuse() {
        let f =
            Faults::parse("no_stage, stage_unplug_after=3,stage_stuck=y,overflow_after_reads=2")
                .unwrap();
        assert!(f.no_stage);
        assert_eq!(f.stage_unplug_after, Some(3));
        assert_eq!(f.stage_stuck, [false, true, false]);
        assert_eq!(f.overflow_after_reads, Some(2));
        let e = Faults::parse("stage_unplug_after=x").unwrap_err();
        assert!(
            e.contains("stage_unplug_after=x") && e.contains("whole number"),
            "{e}"
        );
        assert!(Faults::parse("explode").unwrap_err().contains("unknown"));
        assert_eq!(Faults::parse("none").unwrap(), Faults::default());
    }

    #[test]
    fn wiring_and_settings() {
        let mut c = Config::default();
        c.set("wiring", "ai3=y_monitor, ao0=open, ao1=x").unwrap();
        assert_eq!(c.ai[3], AiSource::Monitor(1));
        assert_eq!(c.ao, [None, Some(0)]);
        let e = c.set("wiring", "ai4=sx").unwrap_err();
        assert!(e.contains("ai4=sx"), "{e}");
        let e = c.set("tau_ms", "-1").unwrap_err();
        assert!(
            e.contains("tau_ms") && e.contains("-1") && e.contains("0–1000"),
            "{e}"
        );
        c.set("range_um", "100, 100, 20").unwrap();
        assert_eq!(c.origin(), [50.0, 50.0, 10.0]);
    }
}
