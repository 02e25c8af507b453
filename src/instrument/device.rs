//! The words every instrument file shares: a stage position and a device error (a leaf: the
//! drivers and the traits in `instrument/mod.rs` use it, it uses none of them).

/// Stage position (x, y, z) in µm.
pub type Pos = [f64; 3];

/// Axis names used everywhere at the script boundary.
pub const AXES: [&str; 3] = ["x", "y", "z"];

/// A device error. Every variant names the device and, where there is one, the command and
/// what came back, so the message a scientist sees at the prompt says what happened.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DeviceError {
    #[error("{device}: no reply to `{command}` within {timeout_ms} ms")]
    Timeout {
        device: String,
        command: String,
        timeout_ms: u64,
    },
    #[error("{device}: garbled reply to `{command}`: {reply:?}")]
    Garbled {
        device: String,
        command: String,
        reply: String,
    },
    #[error("{device}: controller error {code} after `{command}`: {message}")]
    Controller {
        device: String,
        command: String,
        code: i64,
        message: String,
    },
    #[error("{device}: disconnected during `{command}`: {detail}")]
    Disconnected {
        device: String,
        command: String,
        detail: String,
    },
    #[error("{device}: {detail}")]
    Other { device: String, detail: String },
}

/// `f` on every one of `items`, also after one fails (a stop or a hold must reach every axis and
/// every controller); the first error, if any (what the calls return otherwise is dropped).
pub fn all_then_first_error<T, R>(
    items: impl IntoIterator<Item = T>,
    f: impl FnMut(T) -> Result<R, DeviceError>,
) -> Result<(), DeviceError> {
    let mut first = None;
    for r in items.into_iter().map(f) {
        if let Err(e) = r {
            first.get_or_insert(e);
        }
    }
    first.map_or(Ok(()), Err)
}

impl DeviceError {
    /// The same error, naming `command` as the one it happened in (e.g. the `ERR?` that
    /// followed a `MOV`: `ERR? (after `MOV A 1.000000`)`). Errors that carry no command are
    /// returned unchanged.
    pub fn during(self, command: &str) -> DeviceError {
        match self {
            DeviceError::Timeout {
                device, timeout_ms, ..
            } => DeviceError::Timeout {
                device,
                command: command.to_string(),
                timeout_ms,
            },
            DeviceError::Garbled { device, reply, .. } => DeviceError::Garbled {
                device,
                command: command.to_string(),
                reply,
            },
            DeviceError::Disconnected { device, detail, .. } => DeviceError::Disconnected {
                device,
                command: command.to_string(),
                detail,
            },
            other => other,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn all_then_first_error_calls_every_item_and_returns_the_first_error() {
        let fail = |i: usize| DeviceError::Other {
            device: format!("controller {i}"),
            detail: "no reply".into(),
        };
        let mut called = Vec::new();
        let r = all_then_first_error(0..4, |i| {
            called.push(i);
            if i == 1 || i == 2 {
                Err(fail(i))
            } else {
                Ok(())
            }
        });
        assert_eq!(called, [0, 1, 2, 3]);
        assert_eq!(r.unwrap_err().to_string(), fail(1).to_string());
        assert!(all_then_first_error(0..3, |_| Ok(())).is_ok());
    }
}
