//! Binding family `hardware`: raw access to a connected controller for debugging, queries only
//! (issue 16 item 7). Motion never goes through here: it goes through the engine's checks.

use super::ctx::Ctx;
use super::registry::{fail, Doc, RResult, Registrar};
use rhai::{Array, Dynamic};

pub fn register(r: &mut Registrar) {
    let c = r.ctx();
    r.bind(
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
        move |q: &str| gcs_query(&c, q),
    );
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
