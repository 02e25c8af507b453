//! Binding family `hardware`: raw access to a connected controller for debugging, queries only.
//! Motion never goes through here: it goes through the engine's checks.

use super::ctx::Ctx;
use super::registry::{fail, Doc, RResult, Registrar};
use rhai::{Array, Dynamic};

pub fn register(r: &mut Registrar) {
    r.bind_ctx(
        Doc::func("gcs_query")
            .arg("query", "string", "", "a GCS query: a command ending in `?`, e.g. \"SAI?\", \"POS? 1\", \"VEL?\", \"*IDN?\"")
            .returns("array", "the reply lines")
            .summary("send a raw query to the connected PI (GCS) controller and return its reply")
            .help(
                "For debugging at the bench: what the controller itself says (axis identifiers \
                 `SAI?`, servo state `SVO?`, targets `MOV?`, velocities `VEL?`, the last error \
                 `ERR?`). Only queries are sent; anything else (`MOV`, `SVO`, `STP`, …) is \
                 refused before it reaches the port, because motion goes through mv, mvr and the \
                 scans and their safety checks. On the simulator or the mock there is no \
                 controller language, and the call says so.",
            )
            .example(
                "connect(#{backend: \"mock\"}); gcs_query(\"SAI?\")",
                "error: gcs_query: mock stage: `SAI?`: this stage has no command language to query",
            ),
        |c| move |q: &str| gcs_query(&c, q),
    );
    r.bind_ctx(
        Doc::func("zero_gauge")
            .returns("map", "#{x, y, z}: true for each axis whose strain gauge is now zeroed")
            .summary("zero the strain gauges of the stage's piezo cubes (Thorlabs KPZ101)")
            .help(
                "A KPZ101 measures its closed-loop position with the actuator's strain gauge, whose \
                 reading carries an offset until the gauge is zeroed: positions read back are then \
                 not the positions. zero_gauge() sends MGMSG_PZ_SET_ZERO to each cube in turn (x, \
                 y, z) and waits for its \"zeroed\" status bit, at most [stage] zero_timeout_ms \
                 (default 60 s) per cube. Zeroing drives the actuator to 0 V, its zero, a move of \
                 up to the whole travel: nothing must touch the sample. The cube then holds there. \
                 Whether each gauge was zeroed is in status().instrument.stage.gauge_zeroed and in \
                 every scan's metadata (meta.instrument.stage.gauge_zeroed); connect() warns about a \
                 gauge that is not zeroed, and [stage] zero_at_connect = true zeroes at connect. A \
                 cube that does not report \"zeroed\" in time is told to hold where it is and the \
                 error names it. Stages without a strain gauge to zero (PI controllers, the \
                 simulator, the mock) refuse.",
            )
            .example(
                "connect(#{backend: \"mock\"}); zero_gauge()",
                "error: zero_gauge: mock stage: this stage has no strain gauge to zero (Thorlabs KPZ101 cubes have one; PI controllers calibrate their sensors themselves)",
            ),
        |c| move || zero_gauge(&c),
    );
}

/// `zero_gauge()`: zero every KPZ101 cube's strain gauge, record the state in the instrument
/// description (scan metadata) and return it per axis.
fn zero_gauge(c: &Ctx) -> RResult<rhai::Map> {
    c.with_instrument("zero_gauge", |i| {
        let name = i.stage.name();
        let r = match i.stage.gauge() {
            Some(g) => g.zero_gauge(),
            None => Err(crate::instrument::DeviceError::Other {
                device: name,
                detail: "this stage has no strain gauge to zero (Thorlabs KPZ101 cubes \
                         have one; PI controllers calibrate their sensors themselves)"
                    .into(),
            }),
        };
        crate::config::connect::record_gauge(i);
        let z = r.map_err(|e| format!("zero_gauge: {e}"))?;
        let mut m = rhai::Map::new();
        for (k, v) in ["x", "y", "z"].into_iter().zip(z) {
            m.insert(k.into(), Dynamic::from(v));
        }
        Ok(m)
    })
}

/// `gcs_query(query)`: the reply lines of the connected controller to one raw GCS query; only
/// queries (commands ending in `?`) reach the port, motion is refused by the stage.
fn gcs_query(c: &Ctx, q: &str) -> RResult<Array> {
    if q.trim().is_empty() {
        return fail("gcs_query: query is empty; e.g. gcs_query(\"SAI?\")");
    }
    c.with_instrument("gcs_query", |i| {
        let lines = i
            .stage
            .raw_query(q)
            .map_err(|e| format!("gcs_query: {e}"))?;
        Ok(lines.into_iter().map(Dynamic::from).collect())
    })
}
