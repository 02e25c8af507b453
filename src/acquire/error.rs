//! What a scan that measured nothing ends with (a leaf: the engine and the strategies both
//! return it).

use crate::instrument::DeviceError;

/// Nothing was measured: the plan was refused, or the start position could not be read.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ScanError {
    #[error("{0}")]
    Refused(String),
    #[error("{kind}: {error} (nothing was moved)")]
    Device { kind: String, error: DeviceError },
}
