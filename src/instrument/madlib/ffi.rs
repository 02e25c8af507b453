//! Madlib's C API as declared by Mad City Labs' public header `Madlib.h` (© Mad City Labs
//! 2019, BSD licence; published with Micro-Manager's `DeviceAdapters/MCL_NanoDrive/`), loaded
//! at run time. Only the functions bfpscope calls are declared; each with the header's
//! argument order and C types. `MADLIB_API` is empty in the header: the C calling convention.
//! The header's `bool` is `unsigned char` in C (`typedef unsigned char bool;`), so `u8` here.
//!
//! Two functions are not in the 2019 header but in Madlib's older public declarations and in
//! the library labs use (`MCL_InitHandle`: `int MCL_InitHandle();`, "0 when no device could be
//! grabbed"); they are loaded when present and never required.

use super::super::vendor::{vendor_library, LibrarySpec};
use std::os::raw::{c_double, c_int, c_uint};

/// `#define MCL_SUCCESS 0` and the error codes of `Madlib.h`, with their names.
pub const MCL_SUCCESS: c_int = 0;
pub const MCL_GENERAL_ERROR: c_int = -1;
pub const MCL_DEV_ERROR: c_int = -2;
pub const MCL_DEV_NOT_ATTACHED: c_int = -3;
pub const MCL_USAGE_ERROR: c_int = -4;
pub const MCL_DEV_NOT_READY: c_int = -5;
pub const MCL_ARGUMENT_ERROR: c_int = -6;
pub const MCL_INVALID_AXIS: c_int = -7;
pub const MCL_INVALID_HANDLE: c_int = -8;
pub const MCL_INVALID_DRIVER: c_int = -9;
pub const MCL_SEQ_NOT_VALID: c_int = -10;
pub const MCL_BLOCKED_BY_TIRFLOCK: c_int = -11;

/// The name of a Madlib return code and what it means for the user, or `None` for a code
/// the header does not define.
pub fn code_name(code: c_int) -> Option<(&'static str, &'static str)> {
    Some(match code {
        MCL_SUCCESS => ("MCL_SUCCESS", "success"),
        MCL_GENERAL_ERROR => ("MCL_GENERAL_ERROR", "general error in the library"),
        MCL_DEV_ERROR => ("MCL_DEV_ERROR", "the Nano-Drive reported an error"),
        MCL_DEV_NOT_ATTACHED => (
            "MCL_DEV_NOT_ATTACHED",
            "the Nano-Drive is not attached (USB unplugged or the controller switched off)",
        ),
        MCL_USAGE_ERROR => (
            "MCL_USAGE_ERROR",
            "the function cannot be used with this device",
        ),
        MCL_DEV_NOT_READY => ("MCL_DEV_NOT_READY", "the Nano-Drive is not ready"),
        MCL_ARGUMENT_ERROR => ("MCL_ARGUMENT_ERROR", "an argument is out of range"),
        MCL_INVALID_AXIS => ("MCL_INVALID_AXIS", "the axis is not on this Nano-Drive"),
        MCL_INVALID_HANDLE => ("MCL_INVALID_HANDLE", "the handle is not valid"),
        MCL_INVALID_DRIVER => ("MCL_INVALID_DRIVER", "the USB driver is not the right one"),
        MCL_SEQ_NOT_VALID => ("MCL_SEQ_NOT_VALID", "the sequence is not valid"),
        MCL_BLOCKED_BY_TIRFLOCK => ("MCL_BLOCKED_BY_TIRFLOCK", "blocked by TIRF-Lock"),
        _ => return None,
    })
}

/// `MCL_SingleReadN` and `MCL_GetCalibration` return a `double`: the value, or one of the
/// error codes above as a double. A negative whole number −1…−11 is read as the code (a
/// calibrated position never reads a whole micrometre below the range's 0).
pub fn double_code(v: c_double) -> Option<c_int> {
    (v.is_finite() && (-11.0..=-1.0).contains(&v) && v == v.trunc()).then_some(v as c_int)
}

/// `struct ProductInformation` of `Madlib.h`, declared inside `#pragma pack(push, 1)`.
#[repr(C, packed)]
#[derive(Debug, Clone, Copy, Default)]
pub struct ProductInformation {
    /// Bitmap of the available axes (bit 0 = axis 1 = X, …).
    pub axis_bitmap: u8,
    /// Bits of resolution of the ADC and the DAC.
    pub adc_resolution: i16,
    pub dac_resolution: i16,
    pub product_id: i16,
    pub firmware_version: i16,
    pub firmware_profile: i16,
}

pub type GrabAllHandles = unsafe extern "C" fn() -> c_int;
pub type GetAllHandles = unsafe extern "C" fn(handles: *mut c_int, size: c_int) -> c_int;
pub type ReleaseHandle = unsafe extern "C" fn(handle: c_int);
pub type SingleReadN = unsafe extern "C" fn(axis: c_uint, handle: c_int) -> c_double;
pub type SingleWriteN =
    unsafe extern "C" fn(position: c_double, axis: c_uint, handle: c_int) -> c_int;
pub type GetCalibration = unsafe extern "C" fn(axis: c_uint, handle: c_int) -> c_double;
pub type GetSerialNumber = unsafe extern "C" fn(handle: c_int) -> c_int;
pub type GetProductInfo = unsafe extern "C" fn(pi: *mut ProductInformation, handle: c_int) -> c_int;
pub type DeviceAttached = unsafe extern "C" fn(milliseconds: c_int, handle: c_int) -> u8;
pub type InitHandle = unsafe extern "C" fn() -> c_int;
pub type InitLibrary = unsafe extern "C" fn() -> u8;

/// Where Madlib is looked for.
pub const SPEC: LibrarySpec = LibrarySpec {
    what: "Mad City Labs Madlib",
    config_key: "stage.library",
    env_var: "BFPSCOPE_MADLIB",
    #[cfg(windows)]
    names: &["Madlib.dll"],
    #[cfg(not(windows))]
    names: &["libmadlib.so"],
    #[cfg(windows)]
    paths: &["C:\\Program Files\\Mad City Labs\\NanoDrive\\Madlib.dll"],
    #[cfg(not(windows))]
    paths: &[
        "/usr/local/lib/libmadlib.so",
        "/usr/lib/libmadlib.so",
        "/usr/lib/x86_64-linux-gnu/libmadlib.so",
    ],
};

vendor_library! {
    /// The loaded library and its functions. The pointers stay valid while `_lib` lives.
    pub struct Madlib from SPEC {
        required {
            grab_all_handles: GrabAllHandles = "MCL_GrabAllHandles",
            get_all_handles: GetAllHandles = "MCL_GetAllHandles",
            release_handle: ReleaseHandle = "MCL_ReleaseHandle",
            single_read_n: SingleReadN = "MCL_SingleReadN",
            single_write_n: SingleWriteN = "MCL_SingleWriteN",
            get_calibration: GetCalibration = "MCL_GetCalibration",
            get_serial_number: GetSerialNumber = "MCL_GetSerialNumber",
            get_product_info: GetProductInfo = "MCL_GetProductInfo",
        }
        optional {
            device_attached: DeviceAttached = "MCL_DeviceAttached",
            init_handle: InitHandle = "MCL_InitHandle",
            init_library: InitLibrary = "MCL_InitLibrary",
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn product_information_is_packed_as_the_header_says() {
        // unsigned char + 5 shorts under #pragma pack(1)
        assert_eq!(std::mem::size_of::<ProductInformation>(), 11);
    }

    #[test]
    fn codes_have_the_header_names() {
        assert_eq!(code_name(-3).unwrap().0, "MCL_DEV_NOT_ATTACHED");
        assert_eq!(code_name(-8).unwrap().0, "MCL_INVALID_HANDLE");
        assert_eq!(code_name(-11).unwrap().0, "MCL_BLOCKED_BY_TIRFLOCK");
        assert!(code_name(-12).is_none());
    }

    #[test]
    fn a_double_return_is_a_code_only_when_a_whole_negative_code() {
        assert_eq!(double_code(-3.0), Some(MCL_DEV_NOT_ATTACHED));
        assert_eq!(double_code(-0.02), None); // a reading just below 0 µm
        assert_eq!(double_code(-2.5), None);
        assert_eq!(double_code(75.0), None);
        assert_eq!(double_code(-12.0), None);
        assert_eq!(double_code(f64::NAN), None);
    }
}
