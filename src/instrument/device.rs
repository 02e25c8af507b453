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
