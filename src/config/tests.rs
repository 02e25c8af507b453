//! Tests of the config file's parsing and checks (`config/mod.rs`).

use super::*;
use crate::acquire::limits::DEFAULT_MAX_STEP_UM;
use crate::instrument::{gcs::GCS, scpi::SCPI};

#[test]
fn empty_file_is_simulated() {
    let c = Config::from_toml_str("", "t").unwrap();
    assert!(c.is_simulated());
    assert_eq!(c, Config::default());
}

#[test]
fn full_config_round_trip() {
    let text = r#"
[stage]
backend = "gcs"
port = "/dev/ttyUSB0"
baud = 57600
axes = { x = "1", y = "2", z = "3" }
settle_s = 0.01

[qpd]
backend = "scpi"
port = "/dev/ttyUSB1"
calibration = { gain = [2.0, 2.0, 0.5], offset_v = [0.1, 0.0, 0.0] }

[safety]
soft_limits = { x = [10, 90], z = [1.0, 19.0] }
max_step_um = 5.0
max_speed_um_s = 200

[optics]
wavelength_nm = 1064.0
"#;
    let c = Config::from_toml_str(text, "t").unwrap();
    assert_eq!(c.stage.backend, GCS);
    assert_eq!(c.stage.baud, 57600);
    assert_eq!(
        crate::instrument::gcs::config::options(&c.stage).axes,
        crate::instrument::gcs::axes_xyz(["1", "2", "3"])
    );
    assert_eq!(c.qpd.calibration.gain, [2.0, 2.0, 0.5]);
    assert_eq!(c.safety.soft_limits.x, Some([10.0, 90.0])); // integers are fine
    assert_eq!(c.safety.soft_limits.y, None);
    assert_eq!(c.safety.max_step_um, Some(5.0));
    let l = c.soft_limits();
    assert_eq!(l.range[0], (10.0, 90.0));
    assert_eq!(l.range[1], (f64::NEG_INFINITY, f64::INFINITY));
    assert_eq!((l.max_step_um, l.max_speed_um_s), (5.0, Some(200.0)));
    assert_eq!(c.optics.wavelength_nm, Some(1064.0));
    let again = Config::from_toml_str(&c.to_toml(), "t2").unwrap();
    assert_eq!(again, c);
}

fn error_of(text: &str) -> ConfigError {
    Config::from_toml_str(text, "bfpscope.toml").unwrap_err()
}

/// The error of `text`, which must name `key`.
fn refused_at(text: &str, key: &str) -> ConfigError {
    let e = error_of(text);
    assert_eq!(e.key, key, "{e}");
    e
}

#[test]
fn misspelled_tables_are_refused_with_the_nearest_name() {
    // a typo in [safety] must not drop the soft limits silently
    let e = error_of("[stage]\nbackend = \"sim\"\n\n[saftey]\nsoft_limits = { x = [-5.0, 5.0] }\n");
    assert_eq!((e.key.as_str(), e.line), ("saftey", Some(4)), "{e}");
    assert!(
        e.message
            .starts_with("unknown field `saftey`; did you mean `safety`?"),
        "{e}"
    );
    assert!(e.to_string().starts_with("bfpscope.toml: saftey: "), "{e}");
    // a misspelled or capitalised [stage] naming hardware must not start the simulator
    for (text, word, nearest) in [
        (
            "[stagee]\nbackend = \"gcs\"\nport = \"/dev/x\"\n",
            "stagee",
            "stage",
        ),
        (
            "[Stage]\nbackend = \"gcs\"\nport = \"/dev/x\"\n",
            "Stage",
            "stage",
        ),
        ("[qdp]\nbackend = \"scpi\"\n", "qdp", "qpd"),
        ("[optic]\nwavelength_nm = 800\n", "optic", "optics"),
    ] {
        let e = error_of(text);
        assert_eq!((e.key.as_str(), e.line), (word, Some(1)), "{e}");
        assert!(
            e.message.starts_with(&format!(
                "unknown field `{word}`; did you mean `{nearest}`?"
            )),
            "{e}"
        );
    }
    // a name far from every table: no guess, the list
    let e = error_of("[frobnicate]\nx = 1\n");
    assert_eq!(
        e.message,
        "unknown field `frobnicate`, expected one of `stage`, `qpd`, `safety`, `raster`, `sandbox`, `session`, `optics`"
    );
}

#[test]
fn unknown_keys_in_every_table_name_the_nearest() {
    for (text, key, nearest, line) in [
        (
            "[sandbox]\nmax_operation = 5\n",
            "sandbox.max_operation",
            "max_operations",
            2,
        ),
        (
            "[session]\ndata_dri = \"x\"\n",
            "session.data_dri",
            "data_dir",
            2,
        ),
        (
            "\n[optics]\nwavelenght_nm = 800\n",
            "optics.wavelenght_nm",
            "wavelength_nm",
            3,
        ),
        (
            "[safety]\nmax_step = 2.0\n",
            "safety.max_step",
            "max_step_um",
            2,
        ),
    ] {
        let e = error_of(text);
        assert_eq!((e.key.as_str(), e.line), (key, Some(line)), "{e}");
        assert!(
            e.message.contains(&format!("; did you mean `{nearest}`?")),
            "{e}"
        );
    }
}

#[test]
fn optics_table_is_read_and_checked() {
    let c =
        Config::from_toml_str("[optics]\nwavelength_nm = 800\nbeam = \"paraxial\"\n", "t").unwrap();
    let o = c.optics.resolve().unwrap();
    assert_eq!(
        (o.wavelength_nm, o.beam),
        (800.0, crate::optics::Beam::Paraxial)
    );
    // the keys left out keep the defaults
    let d = crate::optics::Optics::default();
    assert_eq!((o.na, o.w0_nm, o.n_medium), (d.na, d.w0_nm, d.n_medium));
    let e = error_of("[optics]\nna = 2.5\n");
    assert_eq!((e.key.as_str(), e.line), ("optics.na", Some(2)), "{e}");
    assert_eq!(e.message, "na = 2.5 is out of range: 0.01 ≤ na ≤ 1.7");
    let e = refused_at("[optics]\nbeam = \"gaussian\"\n", "optics.beam");
    assert!(
        e.message
            .contains("beam = \"gaussian\" is not a beam model"),
        "{e}"
    );
    let e = error_of("[sandbox]\nmax_operations = 0\n");
    assert_eq!(
        (e.key.as_str(), e.line),
        ("sandbox.max_operations", Some(2)),
        "{e}"
    );
    refused_at("[session]\ndata_dir = \" \"\n", "session.data_dir");
    // [sandbox] and [session] as read
    let c = Config::from_toml_str(
        "[sandbox]\nmax_operations = 1000\n[session]\ndata_dir = \"/tmp/d\"\n",
        "t",
    )
    .unwrap();
    assert_eq!(c.sandbox.max_operations, 1000);
    assert_eq!(
        c.sandbox.max_call_levels,
        Sandbox::default().max_call_levels
    );
    assert_eq!(c.session.data_dir.as_deref(), Some("/tmp/d"));
}

#[test]
fn parse_errors_name_the_key_path() {
    let e = refused_at(
        "[stage]\nbackend = \"gcs\"\nport = \"/dev/x\"\nbaud = \"fast\"\n",
        "stage.baud",
    );
    assert_eq!(e.line, Some(4));
    assert!(e.message.contains("invalid type"), "{e}");
    assert_eq!(
        e.to_string(),
        "bfpscope.toml: stage.baud: invalid type: string \"fast\", expected u32 (line 4)"
    );

    let e = error_of("[stage]\nbackend = \"gsc\"\n");
    assert_eq!((e.key.as_str(), e.line), ("stage.backend", Some(2)));
    assert!(e.message.contains("gsc"), "{e}");

    let e = refused_at(
        "[safety]\nsoft_limits = { x = [0.0, 1.0] }\nmax_step = 2.0\n",
        "safety.max_step",
    );
    assert_eq!(
        e.to_string(),
        "bfpscope.toml: safety.max_step: unknown field `max_step`; did you mean `max_step_um`? \
         (known: `soft_limits`, `max_step_um`, `max_speed_um_s`) (line 3)"
    );
    let e = error_of("[safety]\nsoft_limits = { w = [0.0, 1.0] }\n");
    assert_eq!((e.key.as_str(), e.line), ("safety.soft_limits", Some(2)));
    assert!(e.message.contains("unknown field `w`"), "{e}");

    refused_at(
        "[qpd.calibration]\ngain = [1.0, 2.0]\n",
        "qpd.calibration.gain",
    );
}

#[test]
fn validation_errors_name_the_key_path() {
    let e = refused_at(
        "[stage]\nbackend = \"gcs\"\n[qpd]\nbackend = \"scpi\"\nport = \"/dev/b\"\n",
        "stage.port",
    );
    assert_eq!(e.line, None, "must not point at qpd.port");
    assert_eq!(
        e.to_string(),
        "bfpscope.toml: stage.port: required when backend = \"gcs\" (e.g. \"/dev/ttyUSB0\" or \
         \"tcp://192.168.0.10:50000\"; or stage.ports = { x = …, y = …, z = … } for a stage split \
         across controllers)"
    );
    refused_at(
        "[stage]\nbackend = \"gcs\"\nport = \"/dev/a\"\n",
        "qpd.backend",
    );
    let e =
        error_of("[safety]\nmax_step_um = 1.0\nsoft_limits = { y = [0.0, 1.0], x = [5.0, 1.0] }\n");
    assert_eq!(e.key, "safety.soft_limits.x");
    assert_eq!(e.line, Some(3));
    let e = refused_at(
        "[stage]\naxes = { x = \"1\", y = \"1\", z = \"3\" }\n",
        "stage.axes",
    );
    assert!(
        e.message
            .starts_with("x and y are both \"1\" on one controller"),
        "{e}"
    );
    refused_at(
        "[qpd]\ncalibration = { gain = [0.0, 1.0, 1.0] }\n",
        "qpd.calibration.gain",
    );
    refused_at("[safety]\nmax_step_um = -1.0\n", "safety.max_step_um");
    let e = error_of("\n[safety]\nmax_speed_um_s = 0.0\n");
    assert_eq!((e.key.as_str(), e.line), ("safety.max_speed_um_s", Some(3)));
    assert!(e.message.contains("positive"), "{e}");
}

#[test]
fn legacy_tables_are_refused_with_their_safety_equivalent() {
    let e = error_of("[stage]\nbaud = 9600\n\n[limits]\nx = [5.0, 95.0]\nmax_step_um = 2.0\n");
    assert_eq!((e.key.as_str(), e.line), ("limits", Some(4)));
    assert_eq!(
        e.message,
        "the [limits] table is now [safety] (same meanings; max_step_um is the largest pixel pitch of a \
         scan): write [safety] soft_limits = { x = [5.0, 95.0] }, max_step_um = 2.0"
    );
    // the suggested text is a valid config with the same meaning
    let c = Config::from_toml_str(
        "[safety]\nsoft_limits = { x = [5.0, 95.0] }\nmax_step_um = 2.0\n",
        "t",
    )
    .unwrap();
    assert_eq!(c.soft_limits().range[0], (5.0, 95.0));
    assert_eq!(c.soft_limits().max_step_um, 2.0);
    let e = error_of("[stage]\nbaud = 9600\nmax_speed_um_s = 500.0\n");
    assert_eq!((e.key.as_str(), e.line), ("stage.max_speed_um_s", Some(3)));
    assert!(
        e.message
            .starts_with("moved to [safety]: write `max_speed_um_s = 500.0` in [safety]"),
        "{e}"
    );
}

#[test]
fn raster_keys_are_checked_and_reach_the_driver() {
    let e = error_of("[stage]\nsettle_s = 0.01\ntrigger_line = 4\n");
    assert_eq!((e.key.as_str(), e.line), ("stage.trigger_line", Some(3)));
    assert!(
        e.message.starts_with("4: ") && e.message.contains("1, 2 or 3"),
        "{e}"
    );
    let e = refused_at("[stage]\nservo_cycle_s = -5e-5\n", "stage.servo_cycle_s");
    assert!(e.message.starts_with("-0.00005: "), "{e}");
    refused_at(
        "[stage]\nmax_record_points = 0\n",
        "stage.max_record_points",
    );
    let c =
        Config::from_toml_str("[stage]\ntrigger_line = 2\nservo_cycle_s = 4e-5\n", "t").unwrap();
    let o = crate::instrument::gcs::config::options(&c.stage);
    assert_eq!((o.trigger_line, o.servo_cycle_s), (Some(2), Some(4e-5)));
    assert_eq!((o.max_wave_points, o.max_record_points), (None, None));
}

#[test]
fn example_file_parses() {
    let c = Config::from_toml_str(
        include_str!("../../docs/bfpscope.example.toml"),
        "bfpscope.example.toml",
    )
    .unwrap();
    assert_eq!((c.stage.backend, c.qpd.backend), (GCS, SCPI));
    assert_eq!(c.stage.port.as_deref(), Some("/dev/ttyUSB0"));
    assert_eq!(c.safety.soft_limits.z, Some([1.0, 19.0]));
    assert_eq!(c.soft_limits().max_step_um, DEFAULT_MAX_STEP_UM);
    // every key shown with its default really is the default
    let d = Config::default();
    assert_eq!(
        (
            c.stage.baud,
            c.stage.timeout_ms,
            c.stage.on_target_timeout_ms,
            c.stage.poll_ms,
            c.stage.settle_s
        ),
        (
            d.stage.baud,
            d.stage.timeout_ms,
            d.stage.on_target_timeout_ms,
            d.stage.poll_ms,
            d.stage.settle_s
        )
    );
    assert_eq!(
        (
            &c.stage.axes,
            c.stage.servo_on_connect,
            c.stage.units_per_um,
            c.stage.one_axis_per_query
        ),
        (
            &d.stage.axes,
            d.stage.servo_on_connect,
            d.stage.units_per_um,
            d.stage.one_axis_per_query
        )
    );
    assert_eq!(
        (c.qpd.timeout_ms, c.qpd.statistics, c.qpd.calibration),
        (d.qpd.timeout_ms, d.qpd.statistics, d.qpd.calibration)
    );
    assert_eq!((&c.sandbox, &c.session), (&d.sandbox, &d.session));
    // the example's [optics] names the default wavelength: the optics are the defaults
    assert_eq!(
        c.optics.resolve().unwrap(),
        crate::optics::ValidOptics::default()
    );
}

const HW: &str = "[qpd]\nbackend = \"scpi\"\nport = \"/dev/ttyUSB9\"\n[stage]\nbackend = \"gcs\"\n";

/// The error of a GCS stage and SCPI QPD configuration ([`HW`]) with `stage` added to `[stage]`.
fn hw_error(stage: &str) -> ConfigError {
    error_of(&format!("{HW}{stage}"))
}

#[test]
fn default_axes_are_an_e727s() {
    let c = Config::default();
    assert_eq!(
        [&c.stage.axes.x, &c.stage.axes.y, &c.stage.axes.z],
        ["1", "2", "3"]
    );
}

#[test]
fn tcp_ports_are_checked_naming_key_value_and_allowed_form() {
    let c =
        Config::from_toml_str(&format!("{HW}port = \"tcp://192.168.0.10:50000\"\n"), "t").unwrap();
    assert_eq!(c.stage.distinct_ports(), ["tcp://192.168.0.10:50000"]);
    for bad in [
        "tcp://192.168.0.10",
        "tcp://:50000",
        "tcp://host:0",
        "tcp://host:port",
    ] {
        let e = error_of(&format!("{HW}port = \"{bad}\"\n"));
        assert_eq!(e.key, "stage.port", "{bad}");
        assert_eq!(e.line, Some(6), "{bad}");
        assert_eq!(
            e.message,
            format!(
                "\"{bad}\" is not tcp://HOST:PORT: allowed are a serial port (e.g. \"/dev/ttyUSB0\") or \
                 tcp:// with a host and a port 1–65535 (PI controllers: \"tcp://192.168.0.10:50000\")"
            )
        );
    }
}

#[test]
fn stage_split_across_controllers_groups_axes_by_port() {
    let c = Config::from_toml_str(
        &format!(
            "{HW}ports = {{ x = \"/dev/ttyUSB0\", y = \"/dev/ttyUSB0\", z = \"tcp://10.0.0.2:50000\" }}\n\
             axes = {{ x = \"1\", y = \"2\", z = \"1\" }}\n"
        ),
        "t",
    )
    .unwrap();
    let ctl = crate::instrument::gcs::config::controllers(&c.stage);
    assert_eq!(ctl.len(), 2);
    assert_eq!(ctl[0].0, "/dev/ttyUSB0");
    assert_eq!(
        ctl[0].1.axes,
        [Some("1".to_string()), Some("2".to_string()), None]
    );
    assert_eq!(ctl[1].0, "tcp://10.0.0.2:50000");
    assert_eq!(ctl[1].1.axes, [None, None, Some("1".to_string())]);
    // the same identifier twice on one controller is an error
    let e = hw_error("ports = { x = \"/dev/a\", y = \"/dev/a\", z = \"/dev/b\" }\naxes = { x = \"1\", y = \"1\", z = \"1\" }\n");
    assert_eq!(e.key, "stage.axes");
    assert!(
        e.message
            .starts_with("x and y are both \"1\" on one controller"),
        "{e}"
    );
    // port and ports together
    let e =
        hw_error("port = \"/dev/a\"\nports = { x = \"/dev/a\", y = \"/dev/a\", z = \"/dev/b\" }\n");
    assert_eq!(e.key, "stage.ports");
    assert!(e.message.starts_with("both stage.port = \"/dev/a\" and stage.ports = { x = \"/dev/a\", y = \"/dev/a\", z = \"/dev/b\" } are set"), "{e}");
    // an axis left out, an unknown axis, the QPD on a stage port
    let e = hw_error("ports = { x = \"/dev/a\", y = \"/dev/a\" }\n");
    assert_eq!(e.key, "stage.ports");
    assert!(e.message.contains("missing field `z`"), "{e}");
    let e =
        hw_error("ports = { x = \"/dev/a\", y = \"/dev/a\", z = \"/dev/b\", w = \"/dev/c\" }\n");
    assert!(
        e.message
            .contains("unknown field `w`, expected one of `x`, `y`, `z`"),
        "{e}"
    );
    let e = hw_error("ports = { x = \"/dev/a\", y = \"/dev/a\", z = \"/dev/ttyUSB9\" }\n");
    assert_eq!(e.key, "qpd.port");
    assert_eq!(
        e.message,
        "\"/dev/ttyUSB9\": the stage and the QPD cannot share one port"
    );
}

#[test]
fn key_path_tracker() {
    let t = "a = 1\n[x.y]\nb = 2\nc = [\n  1,\n]\n";
    assert_eq!(key_path_at(t, 0), ("a".into(), 1));
    assert_eq!(key_path_at(t, t.find("b =").unwrap()), ("x.y.b".into(), 3));
    assert_eq!(key_path_at(t, t.find("  1").unwrap()), ("x.y.c".into(), 5));
    let t = "[scene]\npoints = [\n  [1, 2],\n  [x],\n]\n";
    assert_eq!(key_path_at(t, t.find("[x]").unwrap()).0, "scene.points");
}

#[test]
fn bad_safety_table_is_an_error_naming_the_key() {
    let safety = |t: &str| {
        Config::from_toml_str(t, "config")
            .map(|c| c.soft_limits())
            .map_err(|e| e.to_string())
    };
    // each table refused with every fragment its error must hold (the last: the legacy
    // table, refused with its [safety] equivalent)
    let refused: [(&str, &[&str]); 4] = [
        (
            "[safety]\nsoft_limits = { x = [5, -5] }",
            &["safety.soft_limits.x"],
        ),
        (
            "[safety]\nsoft_limits = { w = [0, 1] }",
            &[
                "safety.soft_limits",
                "unknown field `w`, expected one of `x`, `y`, `z`",
            ],
        ),
        (
            "[safety]\nmax_speed_um_s = -3",
            &["config: safety.max_speed_um_s: -3: must be a positive number (µm/s)"],
        ),
        (
            "[limits]\nz = [0.0, 1.0]",
            &["write [safety] soft_limits = { z = [0.0, 1.0] }"],
        ),
    ];
    for (table, fragments) in refused {
        let e = safety(table).unwrap_err();
        for f in fragments {
            assert!(e.contains(f), "{e}");
        }
    }
    // no [safety]: defaults, no speed limit
    let l = safety("[sandbox]\nmax_operations = 5").unwrap();
    assert_eq!(l, SoftLimits::default());
}
