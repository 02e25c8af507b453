//! The device families: one folder of `src/instrument/` each, one line in [`FAMILIES`]. A
//! family declares what the rest of the workbench learns about it here and nowhere else: the
//! `connect` backend names that select it, the `[stage]`/`[qpd]` backends of `bfpscope.toml` it
//! provides, the `connect` map keys it takes, and how it is opened. `config` (which backend is a
//! stage's, which a QPD's), `connect()` (backend names, key checks, the list of backends in its
//! errors) and the REPL read this list. A family known only at run time (a test's, a user's
//! build) joins with [`register_family`].

pub use super::family::{
    Backend, BuildFn, ConnectHelp, Family, Open, Section, StageDefaults, NO_SECTION, STAGE_DEFAULTS,
};
use std::sync::{Mutex, OnceLock};

/// The families built in, one line each (the folder's `FAMILY`).
pub const FAMILIES: &[&Family] = &[
    &super::sim::FAMILY,
    &super::gcs::FAMILY,
    &super::scpi::FAMILY,
    &super::thorlabs::FAMILY,
    &super::redpitaya::FAMILY,
    &super::madlib::FAMILY,
    &super::nidaqmx::FAMILY,
    &super::emulator::FAMILY,
    &super::mock::FAMILY,
];

fn extra() -> &'static Mutex<Vec<Family>> {
    static EXTRA: OnceLock<Mutex<Vec<Family>>> = OnceLock::new();
    EXTRA.get_or_init(|| Mutex::new(Vec::new()))
}

/// Add a family at run time (built into the program or a test, not into this list). Its
/// names must be new: a name another family uses is refused, naming both.
pub fn register_family(f: Family) -> Result<(), String> {
    let names = |f: &Family| -> Vec<&'static str> {
        let mut v = vec![f.name];
        v.extend(f.aliases);
        v.extend(f.stages);
        v.extend(f.qpds);
        v
    };
    let mut extra = extra().lock().unwrap_or_else(|e| e.into_inner());
    // the same family again (a test run twice in one process): nothing to add
    if extra
        .iter()
        .any(|e| e.name == f.name && e.backend == f.backend)
    {
        return Ok(());
    }
    for other in FAMILIES.iter().copied().chain(extra.iter()) {
        if let Some(n) = names(&f).into_iter().find(|n| names(other).contains(n)) {
            return Err(format!(
                "register_family: {n:?} of family {:?} is already a name of family {:?}",
                f.name, other.name
            ));
        }
    }
    extra.push(f);
    Ok(())
}

/// Every family: the built-in ones, then those registered at run time.
pub fn families() -> Vec<Family> {
    let extra = extra().lock().unwrap_or_else(|e| e.into_inner());
    FAMILIES
        .iter()
        .map(|f| **f)
        .chain(extra.iter().copied())
        .collect()
}

/// The family `connect(#{backend})` selects: by its name or one of its aliases, else the
/// first one answering to that backend (`"hardware"`).
pub fn by_backend(name: &str) -> Option<Family> {
    let all = families();
    all.iter()
        .find(|f| f.name == name || f.aliases.contains(&name))
        .or_else(|| all.iter().find(|f| f.backend == name))
        .copied()
}

/// The family providing the `[stage] backend` `name`.
pub fn by_stage(name: &str) -> Option<Family> {
    families().into_iter().find(|f| f.stages.contains(&name))
}

/// The family providing the `[qpd] backend` `name`.
pub fn by_qpd(name: &str) -> Option<Family> {
    families().into_iter().find(|f| f.qpds.contains(&name))
}

/// Every `[stage] backend` value (`qpd: false`) or `[qpd] backend` value (`qpd: true`), in
/// the families' order, each once.
pub fn config_backends(qpd: bool) -> Vec<&'static str> {
    let mut out: Vec<&'static str> = Vec::new();
    for f in families() {
        for b in if qpd { f.qpds } else { f.stages } {
            if !out.contains(b) {
                out.push(b);
            }
        }
    }
    out
}

/// The `[stage]` or `[qpd]` backend named `name`: one some family provides.
pub fn config_backend(name: &str) -> Option<Backend> {
    config_backends(false)
        .into_iter()
        .chain(config_backends(true))
        .find(|b| *b == name)
        .map(Backend)
}

impl<'de> serde::Deserialize<'de> for Backend {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let name = String::deserialize(d)?;
        config_backend(&name).ok_or_else(|| {
            let mut all = config_backends(false);
            for b in config_backends(true) {
                if !all.contains(&b) {
                    all.push(b);
                }
            }
            let all: Vec<String> = all.iter().map(|b| format!("`{b}`")).collect();
            serde::de::Error::custom(format!(
                "unknown variant `{name}`, expected one of {}",
                all.join(", ")
            ))
        })
    }
}

/// The backends a `connect` key applies to (by [`Family::backend`], each once).
pub fn backends_taking(key: &str) -> Vec<&'static str> {
    let mut out: Vec<&'static str> = Vec::new();
    for f in families().iter().filter(|f| f.keys.contains(&key)) {
        if !out.contains(&f.backend) {
            out.push(f.backend);
        }
    }
    out
}

/// Every `connect` key some family takes.
pub fn all_keys() -> Vec<&'static str> {
    let mut out: Vec<&'static str> = Vec::new();
    for f in families() {
        for k in f.keys {
            if !out.contains(k) {
                out.push(k);
            }
        }
    }
    out
}

/// The backend names `connect` accepts, for its error: `"config"`, then each backend with
/// the family names and aliases that also select it (`"thorlabs" ("kpz101", "kpa101")`).
pub fn available() -> String {
    let all = families();
    let mut out = vec!["\"config\"".to_string()];
    let mut seen: Vec<&str> = Vec::new();
    for f in &all {
        if seen.contains(&f.backend) {
            continue;
        }
        seen.push(f.backend);
        let mut more: Vec<&str> = Vec::new();
        for g in all.iter().filter(|g| g.backend == f.backend) {
            for n in std::iter::once(&g.name).chain(g.aliases) {
                if *n != f.backend && !more.contains(n) {
                    more.push(n);
                }
            }
        }
        let q = |v: &[&str]| {
            v.iter()
                .map(|n| format!("{n:?}"))
                .collect::<Vec<_>>()
                .join(", ")
        };
        out.push(if more.is_empty() {
            format!("{:?}", f.backend)
        } else {
            format!("{:?} ({})", f.backend, q(&more))
        });
    }
    out.join(", ")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn backends_select_their_family() {
        assert_eq!(by_backend("hardware").map(|f| f.name), Some("gcs"));
        assert_eq!(by_backend("kpa101").map(|f| f.name), Some("thorlabs"));
        assert_eq!(by_backend("bench").map(|f| f.name), Some("madlib"));
        assert_eq!(by_backend("emulated").map(|f| f.name), Some("emulator"));
        assert!(by_backend("hexapod").is_none());
        assert_eq!(by_stage("kpz101").map(|f| f.backend), Some("thorlabs"));
        assert_eq!(config_backends(false), ["sim", "gcs", "kpz101", "madlib"]);
        assert_eq!(
            config_backends(true),
            ["sim", "scpi", "kpa101", "redpitaya", "nidaqmx"]
        );
        assert_eq!(
            backends_taking("timeout_ms"),
            ["hardware", "thorlabs", "bench"]
        );
    }

    #[test]
    fn a_name_taken_is_refused() {
        let f = Family {
            aliases: &["kpz101"],
            ..Family::new("twin", "twin", Open::Mock)
        };
        let e = register_family(f).unwrap_err();
        assert!(
            e.contains("\"kpz101\" of family \"twin\" is already a name of family \"thorlabs\""),
            "{e}"
        );
    }
}
