//! The paper's bench in `bfpscope.toml`: a Mad City Labs Nano-Drive (`[stage] backend =
//! "madlib"`), an NI DAQ board as the QPD digitiser (`[qpd] backend = "nidaqmx"`) and the NI
//! board's hardware-timed raster (`[raster] backend = "nidaqmx"`).
//!
//! ```toml
//! [stage]
//! backend = "madlib"
//! library = "/usr/local/lib/libmadlib.so"   # optional; default: the usual names and paths
//! serial = 2847                              # optional; default: the only Nano-Drive attached
//! axes = { x = 1, y = 2, z = 3 }             # Madlib axis numbers (1 = X, 2 = Y, 3 = Z, 4 = A)
//! tolerance_um = 0.05                        # on target when the read-back is this close
//!
//! [qpd]
//! backend = "nidaqmx"
//! library = "/usr/lib/x86_64-linux-gnu/libnidaqmx.so"   # optional
//! device = "Dev1"
//! channels = { sx = "ai0", sy = "ai1", sum = "ai2" }    # or q1..q4
//! range_v = 10.0
//! terminal = "diff"
//! rate_hz = 800000.0
//!
//! [raster]
//! backend = "nidaqmx"
//! ao = { x = "ao0", y = "ao1" }
//! volts_per_um = { x = 0.1333, y = 0.1333 }
//! position = { x = "ai3" }
//! position_volts_per_um = { x = 0.1333 }
//! external_input = "sum"                    # or "replace"; docs/hardware.md §12 says how to check
//! ```

use super::kinds::{PCI6120_MAX_RANGE_V, PCI6120_MAX_RATE_HZ};
use super::{err, Config, ConfigError};
use crate::instrument::madlib::MadlibOptions;
use crate::instrument::nidaqmx::raster::{ExternalInput, NiRasterOptions};
use crate::instrument::nidaqmx::{parse_channel, NiInputs, NiQpdOptions, Terminal};
use crate::instrument::{madlib::MADLIB, nidaqmx::NIDAQMX, scpi::SCPI};
use std::time::Duration;

fn positive_or_err(key: &str, v: Option<f64>, what: &str) -> Result<f64, ConfigError> {
    match v {
        Some(v) if v.is_finite() && v > 0.0 => Ok(v),
        Some(v) => Err(err(key, format!("{v}: {what} must be a positive number of volts per µm (e.g. 0.1333: 10 V over 75 µm)"))),
        None => Err(err(key, format!("required: {what} in volts per µm (e.g. 0.1333: 10 V over 75 µm)"))),
    }
}

/// Refuse the first of `keys` (key, whether it is set) that is set although it applies only to
/// `backend`; `is` says what the device's backend is instead.
fn only_for<const N: usize>(
    backend: &str,
    is: &str,
    keys: [(&str, bool); N],
) -> Result<(), ConfigError> {
    match keys.into_iter().find(|(_, set)| *set) {
        Some((key, _)) => Err(err(key, format!("only for backend = \"{backend}\" ({is})"))),
        None => Ok(()),
    }
}

impl Config {
    /// The checks of the bench's keys (called by `validate`).
    pub(super) fn validate_bench(&self) -> Result<(), ConfigError> {
        let s = &self.stage;
        let q = &self.qpd;
        if s.backend == MADLIB {
            self.madlib_options()?;
        } else {
            only_for(
                "madlib",
                &format!("the stage is \"{}\"", s.backend.as_str()),
                [
                    ("stage.library", s.library.is_some()),
                    ("stage.serial", s.serial.is_some()),
                ],
            )?;
        }
        if q.backend == NIDAQMX {
            self.ni_qpd_options()?;
        } else {
            only_for(
                "nidaqmx",
                &format!("the QPD is \"{}\"", q.backend.as_str()),
                [
                    ("qpd.library", q.library.is_some()),
                    ("qpd.device", q.device.is_some()),
                    // the SCPI digitiser's range comes from the config too
                    ("qpd.range_v", q.range_v.is_some() && q.backend != SCPI),
                    ("qpd.terminal", q.terminal.is_some()),
                    ("qpd.rate_hz", q.rate_hz.is_some()),
                ],
            )?;
            if let super::QpdChannels::Names(_) = q.channels {
                return Err(err(
                    "qpd.channels",
                    format!(
                        "input names (\"ai0\"…) are for backend = \"nidaqmx\"; the QPD is \"{}\" (a Red Pitaya's inputs are numbers 1–4)",
                        q.backend.as_str()
                    ),
                ));
            }
        }
        if let Some(r) = &self.raster {
            if r.backend != NIDAQMX {
                return Err(err(
                    "raster.backend",
                    format!(
                        "\"{}\": allowed is \"nidaqmx\" (the NI board's hardware-timed raster)",
                        r.backend.as_str()
                    ),
                ));
            }
            if q.backend != NIDAQMX {
                return Err(err("raster.backend", format!("\"nidaqmx\" needs [qpd] backend = \"nidaqmx\" (the raster records the QPD on the NI board); the QPD is \"{}\"", q.backend.as_str())));
            }
            if s.backend != MADLIB {
                return Err(err("raster.backend", format!("\"nidaqmx\" drives a Nano-Drive's external inputs: needs [stage] backend = \"madlib\" (the stage is \"{}\")", s.backend.as_str())));
            }
            self.ni_raster_options()?;
        }
        Ok(())
    }

    /// Nano-Drive driver settings from `[stage]`.
    pub fn madlib_options(&self) -> Result<MadlibOptions, ConfigError> {
        let s = &self.stage;
        let mut axes = [0u32; 3];
        for (i, a) in axes.iter_mut().enumerate() {
            let v = s.axes.get(i);
            *a = match v.trim().parse::<u32>() {
                Ok(n) if (1..=4).contains(&n) => n,
                _ => {
                    return Err(err(
                        &format!("stage.axes.{}", super::AXIS_NAMES[i]),
                        format!("{v:?} is not a Nano-Drive axis: allowed are 1–4 (1 = X, 2 = Y, 3 = Z, 4 = A)"),
                    ))
                }
            };
        }
        if let Some(n) = s.serial {
            if n <= 0 {
                return Err(err("stage.serial", format!("{n}: a Nano-Drive serial number is a positive number (the label on the controller, or MCL_GetSerialNumber)")));
            }
        }
        if let Some(p) = &s.library {
            if p.as_os_str().is_empty() {
                return Err(err("stage.library", "empty: the path of libmadlib.so (or Madlib.dll), or leave the key out to search the usual places"));
            }
        }
        if !(s.tolerance_um.is_finite() && s.tolerance_um > 0.0 && s.tolerance_um <= 10.0) {
            return Err(err(
                "stage.tolerance_um",
                format!("{}: must be above 0 and at most 10 µm", s.tolerance_um),
            ));
        }
        Ok(MadlibOptions {
            library: s.library.clone(),
            serial: s.serial,
            axes,
            tolerance_um: s.tolerance_um,
            on_target_timeout: Duration::from_millis(s.on_target_timeout_ms),
            poll_interval: Duration::from_millis(s.poll_ms()),
        })
    }

    /// NI QPD driver settings from `[qpd]`.
    pub fn ni_qpd_options(&self) -> Result<NiQpdOptions, ConfigError> {
        let q = &self.qpd;
        let device = q.device.clone().unwrap_or_default();
        if device.trim().is_empty() || device.contains('/') || device.contains(char::is_whitespace)
        {
            return Err(err(
                "qpd.device",
                if q.device.is_none() {
                    "required when backend = \"nidaqmx\": the board's name in NI MAX (e.g. \"Dev1\")".to_string()
                } else {
                    format!("{device:?} is not a device name: the board's name in NI MAX (e.g. \"Dev1\")")
                },
            ));
        }
        let names = match &q.channels {
            super::QpdChannels::Names(m) => m.clone(),
            super::QpdChannels::Inputs(_) => {
                return Err(err(
                    "qpd.channels",
                    "required as input names when backend = \"nidaqmx\": { sx = \"ai0\", sy = \"ai1\", sum = \"ai2\" } or { q1 = \"ai0\", q2 = \"ai1\", q3 = \"ai2\", q4 = \"ai3\" }",
                ))
            }
        };
        let ch = |k: &str| -> Result<String, ConfigError> {
            parse_channel("ai", &names[k], &device)
                .map_err(|m| err(&format!("qpd.channels.{k}"), m))
        };
        let keys: Vec<&str> = names.keys().map(String::as_str).collect();
        let inputs = if keys == ["sum", "sx", "sy"] {
            NiInputs::Signals {
                sx: ch("sx")?,
                sy: ch("sy")?,
                sum: ch("sum")?,
            }
        } else if keys == ["q1", "q2", "q3", "q4"] {
            NiInputs::Quadrants([ch("q1")?, ch("q2")?, ch("q3")?, ch("q4")?])
        } else {
            return Err(err(
                "qpd.channels",
                format!(
                    "keys {}: allowed are sx, sy, sum (the QPD amplifier's outputs) or q1, q2, q3, q4 (the quadrants)",
                    keys.join(", ")
                ),
            ));
        };
        let list = inputs.names();
        for i in 0..list.len() {
            if list[i + 1..].contains(&list[i]) {
                return Err(err(
                    "qpd.channels",
                    format!(
                        "{:?} is given twice: each signal needs its own input",
                        list[i]
                    ),
                ));
            }
        }
        let range_v = q.range_v.unwrap_or(10.0);
        if !(range_v.is_finite() && range_v > 0.0 && range_v <= PCI6120_MAX_RANGE_V) {
            return Err(err("qpd.range_v", format!("{range_v}: the input range ±V, above 0 and at most 42 (PCI-6120: 0.2, 0.5, 1, 2, 5, 10, 20, 42)")));
        }
        let terminal = Terminal::parse(q.terminal.as_deref().unwrap_or("diff"))
            .map_err(|m| err("qpd.terminal", m))?;
        let rate_hz = q.rate_hz.unwrap_or(PCI6120_MAX_RATE_HZ);
        if !(rate_hz.is_finite() && rate_hz > 0.0 && rate_hz <= 10e6) {
            return Err(err(
                "qpd.rate_hz",
                format!(
                    "{rate_hz} Hz: the sample rate per channel, above 0 (PCI-6120: at most 800000)"
                ),
            ));
        }
        Ok(NiQpdOptions {
            library: q.library.clone(),
            device,
            inputs,
            range_v,
            terminal,
            rate_hz,
            timeout_margin: Duration::from_millis(q.timeout_ms),
            calibration: q.calibration,
            sum_floor_v: q.sum_floor,
        })
    }

    /// The NI raster's settings from `[raster]` (None without the table).
    pub fn ni_raster_options(&self) -> Result<Option<NiRasterOptions>, ConfigError> {
        let Some(r) = &self.raster else {
            return Ok(None);
        };
        let qo = self.ni_qpd_options()?;
        let dev = qo.device.clone();
        let ao_x = r.ao.x.as_deref().ok_or_else(|| {
            err(
                "raster.ao.x",
                "required: the NI output driving the fast axis's external input (e.g. \"ao0\")",
            )
        })?;
        let ao_x = parse_channel("ao", ao_x, &dev).map_err(|m| err("raster.ao.x", m))?;
        let ao_y = match r.ao.y.as_deref() {
            Some(a) => Some(parse_channel("ao", a, &dev).map_err(|m| err("raster.ao.y", m))?),
            None => None,
        };
        if ao_y.as_deref() == Some(ao_x.as_str()) {
            return Err(err(
                "raster.ao.y",
                format!("{ao_x:?} is raster.ao.x too: each axis needs its own output"),
            ));
        }
        let vx = positive_or_err(
            "raster.volts_per_um.x",
            r.volts_per_um.x,
            "the x external input's scale",
        )?;
        let vy = match ao_y {
            Some(_) => Some(positive_or_err(
                "raster.volts_per_um.y",
                r.volts_per_um.y,
                "the y external input's scale",
            )?),
            None => None,
        };
        if r.position.y.is_some() || r.position_volts_per_um.y.is_some() {
            return Err(err(
                "raster.position.y",
                "only the fast axis's sensor monitor (position.x) is recorded",
            ));
        }
        let px = r.position.x.as_deref().ok_or_else(|| err("raster.position.x", "required: the NI input wired to the fast axis's sensor-monitor output (e.g. \"ai3\")"))?;
        let px = parse_channel("ai", px, &dev).map_err(|m| err("raster.position.x", m))?;
        if qo.inputs.names().contains(&px) {
            return Err(err("raster.position.x", format!("{px:?} is already a QPD input (qpd.channels): the sensor monitor needs its own input")));
        }
        let pvx = positive_or_err(
            "raster.position_volts_per_um.x",
            r.position_volts_per_um.x,
            "the sensor monitor's scale",
        )?;
        let external_input = match r.external_input.as_deref() {
            None => ExternalInput::Sum,
            Some(v) => ExternalInput::parse(v).ok_or_else(|| {
                err(
                    "raster.external_input",
                    format!(
                        "\"{v}\": allowed are \"sum\" (the Nano-Drive adds its external input to the USB command, as MCL documents it; the default) and \"replace\" (it follows the external input alone)"
                    ),
                )
            })?,
        };
        Ok(Some(NiRasterOptions {
            qpd: qo,
            external_input,
            ao: [ao_x, ao_y.unwrap_or_default()],
            volts_per_um: [vx, vy.unwrap_or(0.0)],
            position: px,
            position_volts_per_um: pvx,
        }))
    }
}

/// The fake vendor library the tests build (`libfakebench.so`: Madlib's and NI-DAQmx's
/// symbols over one simulated bench): beside the running binary (`target/<profile>/`), or one
/// folder up (a test binary in `target/<profile>/deps/`).
pub fn fake_bench_library() -> Option<std::path::PathBuf> {
    let name = if cfg!(windows) {
        "fakebench.dll"
    } else if cfg!(target_os = "macos") {
        "libfakebench.dylib"
    } else {
        "libfakebench.so"
    };
    let exe = std::env::current_exe().ok()?;
    let dir = exe.parent()?;
    let found = [
        Some(dir.to_path_buf()),
        Some(dir.join("deps")),
        dir.parent().map(|p| p.to_path_buf()),
    ]
    .into_iter()
    .flatten()
    .map(|d| d.join(name))
    .find(|p: &std::path::PathBuf| p.is_file());
    found
}

/// A `bfpscope.toml` for the fake bench library at `lib` (`bfpscope emulate nidaq`).
pub fn fake_bench_config(lib: &std::path::Path) -> String {
    let l = lib.display().to_string().replace('\\', "/");
    format!(
        r#"# The paper's bench, emulated: a Nano-Drive and an NI PCI-6120 in one fake vendor library
[stage]
backend = "madlib"
library = "{l}"
axes = {{ x = 1, y = 2, z = 3 }}
tolerance_um = 0.05

[qpd]
backend = "nidaqmx"
library = "{l}"
device = "Dev1"
channels = {{ sx = "ai0", sy = "ai1", sum = "ai2" }}
range_v = 10.0
terminal = "diff"
rate_hz = 800000.0

[raster]
backend = "nidaqmx"
ao = {{ x = "ao0", y = "ao1" }}
volts_per_um = {{ x = 0.13333333333333333, y = 0.13333333333333333 }}   # 10 V over 75 µm, exactly
position = {{ x = "ai3" }}
position_volts_per_um = {{ x = 0.13333333333333333 }}
"#
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    const BENCH: &str = r#"
[stage]
backend = "madlib"
library = "/usr/local/lib/libmadlib.so"
serial = 2847
axes = { x = 1, y = 2, z = 3 }

[qpd]
backend = "nidaqmx"
library = "/usr/lib/x86_64-linux-gnu/libnidaqmx.so"
device = "Dev1"
channels = { sx = "ai0", sy = "ai1", sum = "ai2" }
range_v = 10.0
terminal = "diff"
rate_hz = 800000.0

[raster]
backend = "nidaqmx"
ao = { x = "ao0", y = "ao1" }
volts_per_um = { x = 0.1333, y = 0.1333 }
position = { x = "ai3" }
position_volts_per_um = { x = 0.1333 }
"#;

    #[test]
    fn the_issue_config_parses_into_driver_settings() {
        let c = Config::from_toml_str(BENCH, "t").unwrap();
        let m = c.madlib_options().unwrap();
        assert_eq!(m.serial, Some(2847));
        assert_eq!(m.axes, [1, 2, 3]);
        assert_eq!(
            m.library.unwrap().to_str(),
            Some("/usr/local/lib/libmadlib.so")
        );
        let q = c.ni_qpd_options().unwrap();
        assert_eq!(q.device, "Dev1");
        assert_eq!(
            q.inputs,
            NiInputs::Signals {
                sx: "ai0".into(),
                sy: "ai1".into(),
                sum: "ai2".into()
            }
        );
        assert_eq!(q.terminal.daqmx(), 10106);
        assert_eq!(q.rate_hz, 800_000.0);
        let r = c.ni_raster_options().unwrap().unwrap();
        assert_eq!(r.ao, ["ao0".to_string(), "ao1".to_string()]);
        assert_eq!(r.volts_per_um, [0.1333, 0.1333]);
        assert_eq!(r.position, "ai3");
        // and the config round-trips through its TOML
        let again = Config::from_toml_str(&c.to_toml(), "again").unwrap();
        assert_eq!(again, c);
    }

    /// A Nano-Drive settles on its readings: no fixed settle by default (other stages keep
    /// 5 ms); a settle the file gives is kept.
    #[test]
    fn a_nano_drive_has_no_fixed_settle_unless_the_file_gives_one() {
        let c = Config::from_toml_str(BENCH, "t").unwrap();
        assert_eq!(c.stage.settle_s, 0.0);
        let t = BENCH.replace(
            "axes = { x = 1, y = 2, z = 3 }",
            "axes = { x = 1, y = 2, z = 3 }\nsettle_s = 0.01",
        );
        assert_eq!(Config::from_toml_str(&t, "t").unwrap().stage.settle_s, 0.01);
        assert_eq!(Config::default().stage.settle_s, 0.005);
    }

    #[test]
    fn the_emulated_bench_config_is_valid() {
        let c = Config::from_toml_str(
            &fake_bench_config(std::path::Path::new("/t/libfakebench.so")),
            "t",
        )
        .unwrap();
        assert_eq!(
            c.stage.library.as_deref(),
            Some(std::path::Path::new("/t/libfakebench.so"))
        );
        assert_eq!(c.qpd.library, c.stage.library);
        assert!(c.ni_raster_options().unwrap().is_some());
    }

    #[test]
    fn quadrants_are_accepted() {
        let t = BENCH.replace(
            r#"channels = { sx = "ai0", sy = "ai1", sum = "ai2" }"#,
            r#"channels = { q1 = "ai0", q2 = "ai1", q3 = "ai2", q4 = "ai4" }"#,
        );
        let c = Config::from_toml_str(&t, "t").unwrap();
        assert!(matches!(
            c.ni_qpd_options().unwrap().inputs,
            NiInputs::Quadrants(_)
        ));
    }

    fn refused(from: &str, to: &str) -> ConfigError {
        let t = BENCH.replace(from, to);
        assert_ne!(t, BENCH, "{from:?} not in the config");
        Config::from_toml_str(&t, "t").unwrap_err()
    }

    /// `external_input` defaults to MCL's documented "sum", takes "replace", and refuses any
    /// other value naming the key, the value and both choices.
    #[test]
    fn external_input_defaults_to_sum_and_refuses_other_words() {
        let c = Config::from_toml_str(BENCH, "t").unwrap();
        assert_eq!(
            c.ni_raster_options().unwrap().unwrap().external_input,
            ExternalInput::Sum
        );
        let t = BENCH.replace(
            "position_volts_per_um = { x = 0.1333 }",
            "position_volts_per_um = { x = 0.1333 }\nexternal_input = \"replace\"",
        );
        let c = Config::from_toml_str(&t, "t").unwrap();
        assert_eq!(
            c.ni_raster_options().unwrap().unwrap().external_input,
            ExternalInput::Replace
        );
        let again = Config::from_toml_str(&c.to_toml(), "again").unwrap();
        assert_eq!(again.raster, c.raster);
        let e = refused(
            "position_volts_per_um = { x = 0.1333 }",
            "position_volts_per_um = { x = 0.1333 }\nexternal_input = \"add\"",
        );
        assert_eq!(e.key, "raster.external_input");
        assert!(
            e.message.starts_with("\"add\": allowed are \"sum\"")
                && e.message.contains("\"replace\""),
            "{e}"
        );
    }

    #[test]
    fn bad_values_name_the_key_the_value_and_what_is_allowed() {
        let e = refused(r#"sy = "ai1""#, r#"sy = "ai0""#);
        assert_eq!(e.key, "qpd.channels");
        assert!(e.message.contains("\"ai0\" is given twice"), "{e}");
        let e = refused(r#"sum = "ai2""#, r#"sum = "a2""#);
        assert_eq!(e.key, "qpd.channels.sum");
        assert!(
            e.message.contains("\"a2\"") && e.message.contains("\"ai0\" … \"ai63\""),
            "{e}"
        );
        let e = refused(r#"terminal = "diff""#, r#"terminal = "single""#);
        assert_eq!(e.key, "qpd.terminal");
        let e = refused("range_v = 10.0", "range_v = -1.0");
        assert!(e.key == "qpd.range_v" && e.message.starts_with("-1"), "{e}");
        let e = refused("rate_hz = 800000.0", "rate_hz = 0.0");
        assert!(
            e.key == "qpd.rate_hz" && e.message.starts_with("0 Hz"),
            "{e}"
        );
        let e = refused(
            "axes = { x = 1, y = 2, z = 3 }",
            "axes = { x = 1, y = 2, z = 5 }",
        );
        assert_eq!(e.key, "stage.axes.z");
        assert!(
            e.message.contains("\"5\"") && e.message.contains("1–4"),
            "{e}"
        );
        let e = refused("serial = 2847", "serial = -1");
        assert_eq!(e.key, "stage.serial");
        let e = refused(r#"position = { x = "ai3" }"#, r#"position = { x = "ai2" }"#);
        assert_eq!(e.key, "raster.position.x");
        assert!(e.message.contains("already a QPD input"), "{e}");
        let e = refused(
            "volts_per_um = { x = 0.1333, y = 0.1333 }",
            "volts_per_um = { x = 0.1333 }",
        );
        assert_eq!(e.key, "raster.volts_per_um.y");
        let e = refused(
            r#"ao = { x = "ao0", y = "ao1" }"#,
            r#"ao = { x = "ao0", y = "ao0" }"#,
        );
        assert_eq!(e.key, "raster.ao.y");
        let e = refused(r#"ao = { x = "ao0", y = "ao1" }"#, "ao = 5");
        assert_eq!(e.key, "raster.ao");
        assert!(
            e.message
                .contains("expected a table of per-axis values { x = …, y = … }"),
            "{e}"
        );
        let e = refused(r#"device = "Dev1""#, r#"device = "Dev1/ai0""#);
        assert_eq!(e.key, "qpd.device");
        let e = refused(r#"sx = "ai0", "#, r#"sx = 1, "#);
        assert_eq!(e.key, "qpd.channels");
        assert!(e.message.contains("not both"), "{e}");
    }

    #[test]
    fn bench_keys_belong_to_their_backends() {
        let t = "[stage]\nbackend = \"gcs\"\nport = \"/dev/ttyUSB0\"\nserial = 3\n[qpd]\nbackend = \"scpi\"\nport = \"/dev/ttyUSB1\"\n";
        let e = Config::from_toml_str(t, "t").unwrap_err();
        assert_eq!(e.key, "stage.serial");
        assert_eq!(
            e.message,
            "only for backend = \"madlib\" (the stage is \"gcs\")"
        );
        let t = "[stage]\nbackend = \"gcs\"\nport = \"/dev/ttyUSB0\"\n[qpd]\nbackend = \"scpi\"\nport = \"/dev/ttyUSB1\"\nrate_hz = 5.0\n";
        let e = Config::from_toml_str(t, "t").unwrap_err();
        assert_eq!(e.key, "qpd.rate_hz");
        assert_eq!(
            e.message,
            "only for backend = \"nidaqmx\" (the QPD is \"scpi\")"
        );
        let t = "[stage]\nbackend = \"gcs\"\nport = \"/dev/ttyUSB0\"\n[qpd]\nbackend = \"scpi\"\nport = \"/dev/ttyUSB1\"\nchannels = { sx = \"ai0\", sy = \"ai1\", sum = \"ai2\" }\n";
        let e = Config::from_toml_str(t, "t").unwrap_err();
        assert_eq!(e.key, "qpd.channels");
        // a Red Pitaya's numbers still parse as before
        let t = "[stage]\nbackend = \"gcs\"\nport = \"/dev/ttyUSB0\"\n[qpd]\nbackend = \"redpitaya\"\nhost = \"rp\"\nchannels = { sx = 1, sy = 2, sz = 3 }\n";
        let c = Config::from_toml_str(t, "t").unwrap();
        assert_eq!(c.qpd.channels.inputs().sz, Some(3));
    }
}
