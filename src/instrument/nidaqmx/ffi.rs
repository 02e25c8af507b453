//! NI-DAQmx's C API as declared by National Instruments' public header `NIDAQmx.h` (the
//! declarations the `ni-daqmx-sys` crate's Linux bindings copy), loaded at run time. Only the
//! functions bfpscope calls are declared, each with the header's argument order and C types:
//! `int32` = `i32`, `uInt32` = `u32`, `uInt64` = `u64`, `float64` = `f64`, `bool32` = `uInt32`,
//! `TaskHandle` = `void*`. (The header's `int32` is `signed int` under GCC on x86-64 and
//! `signed long` elsewhere, 32 bits on every platform NI-DAQmx runs on: 64-bit Linux, whose
//! `long` is 64 bits, takes the first branch. Older headers, e.g. NI-DAQmx Base's, declared
//! `signed long` unconditionally; PyDAQmx maps it to `c_int`.) The header declares them `__CFUNC`: `__stdcall` on Windows, nothing
//! (the C convention) on Linux and macOS, which is Rust's `extern "system"`.
//!
//! The constants below carry the header's values (`#define DAQmx_Val_…`, `#define
//! DAQmxError…`), checked against its text.

use super::super::vendor::{vendor_library, LibrarySpec};
use std::os::raw::{c_char, c_void};

pub type TaskHandle = *mut c_void;
pub type Bool32 = u32;

// --- values (NIDAQmx.h, "Values for the Mode parameter ..." and attribute value sections) ---
/// `DAQmx_Val_Volts` (units of a voltage channel).
pub const DAQMX_VAL_VOLTS: i32 = 10348;
/// `DAQmx_Val_Rising` / `DAQmx_Val_Falling` (clock and trigger edges).
pub const DAQMX_VAL_RISING: i32 = 10280;
pub const DAQMX_VAL_FALLING: i32 = 10171;
/// `DAQmx_Val_FiniteSamps` / `DAQmx_Val_ContSamps` (sample mode of `DAQmxCfgSampClkTiming`).
pub const DAQMX_VAL_FINITE_SAMPS: i32 = 10178;
pub const DAQMX_VAL_CONT_SAMPS: i32 = 10123;
/// `DAQmx_Val_GroupByChannel` / `DAQmx_Val_GroupByScanNumber` (fill mode, data layout).
pub const DAQMX_VAL_GROUP_BY_CHANNEL: Bool32 = 0;
pub const DAQMX_VAL_GROUP_BY_SCAN_NUMBER: Bool32 = 1;
/// Terminal configurations of `DAQmxCreateAIVoltageChan`.
pub const DAQMX_VAL_CFG_DEFAULT: i32 = -1;
/// `DAQmx_Val_Poll` (Read.WaitMode): a read checks for its samples as fast as it can.
pub const DAQMX_VAL_POLL: i32 = 12524;
pub const DAQMX_VAL_RSE: i32 = 10083;
pub const DAQMX_VAL_NRSE: i32 = 10078;
pub const DAQMX_VAL_DIFF: i32 = 10106;
pub const DAQMX_VAL_PSEUDO_DIFF: i32 = 12529;
/// `DAQmx_Val_WaitInfinitely` (a timeout, s).
pub const DAQMX_VAL_WAIT_INFINITELY: f64 = -1.0;
/// `DAQmx_Val_Task_Commit` / `DAQmx_Val_Task_Unreserve` (`DAQmxTaskControl` actions).
pub const DAQMX_VAL_TASK_COMMIT: i32 = 3;
pub const DAQMX_VAL_TASK_UNRESERVE: i32 = 5;
/// `DAQmx_Val_AllowRegen` / `DAQmx_Val_DoNotAllowRegen` (`DAQmxSetWriteRegenMode`).
pub const DAQMX_VAL_ALLOW_REGEN: i32 = 10097;
pub const DAQMX_VAL_DO_NOT_ALLOW_REGEN: i32 = 10158;

// --- error codes bfpscope names and acts on (NIDAQmx.h `#define DAQmxError…`) ---
pub const DAQMX_ERROR_SAMPLES_NOT_YET_AVAILABLE: i32 = -200284;
pub const DAQMX_ERROR_SAMPLES_NO_LONGER_AVAILABLE: i32 = -200279;
pub const DAQMX_ERROR_DEVICE_REMOVED: i32 = -200045;
pub const DAQMX_ERROR_INVALID_DEVICE_ID: i32 = -200220;
pub const DAQMX_ERROR_DEV_CANNOT_BE_ACCESSED: i32 = -201003;

/// Names of the error codes a user of this bench meets (from `NIDAQmx.h`). Others are shown
/// by number with the library's own text (`DAQmxGetErrorString`).
const ERROR_NAMES: &[(i32, &str)] = &[
    (-200284, "DAQmxErrorSamplesNotYetAvailable"),
    (-200279, "DAQmxErrorSamplesNoLongerAvailable"),
    (-200278, "DAQmxErrorSamplesWillNeverBeAvailable"),
    (-200286, "DAQmxErrorNoAcqStarted"),
    (-200290, "DAQmxErrorGenStoppedToPreventRegenOfOldSamples"),
    (-200045, "DAQmxErrorDeviceRemoved"),
    (-200220, "DAQmxErrorInvalidDeviceID"),
    (-201003, "DAQmxErrorDevCannotBeAccessed"),
    (-200324, "DAQmxErrorDevAbsentOrUnavailable"),
    (-200170, "DAQmxErrorPhysicalChanDoesNotExist"),
    (-201237, "DAQmxErrorInvalidPhysChanName"),
    (-200430, "DAQmxErrorInvalidPhysChanType"),
    (-200431, "DAQmxErrorPhysChanMeasType"),
    (-200086, "DAQmxErrorInvalidSyntaxForPhysicalChannelRange"),
    (-200087, "DAQmxErrorInvalidChannel"),
    (-200077, "DAQmxErrorInvalidAttributeValue"),
    (-200082, "DAQmxErrorMinNotLessThanMax"),
    (-200088, "DAQmxErrorInvalidTask"),
    (-200089, "DAQmxErrorDuplicateTask"),
    (-200096, "DAQmxErrorInvalidNumberSamplesToRead"),
    (-200229, "DAQmxErrorReadBufferTooSmall"),
    (-200332, "DAQmxErrorSampRateTooHigh"),
    (-201093, "DAQmxErrorSampClkRateInvalid"),
    (-200254, "DAQmxErrorInvalidTerm"),
    (-200040, "DAQmxErrorInvalidRoutingSourceTerminalName"),
    (-89120, "DAQmxErrorInvalidRoutingSourceTerminalName_Routing"),
    (-89125, "DAQmxErrorTrigLineNotFound_Routing"),
    (-89136, "DAQmxErrorRouteNotSupportedByHW_Routing"),
    (-200368, "DAQmxErrorRouteNotSupportedByHW"),
    (-200355, "DAQmxErrorPropertyValNotSupportedByHW"),
    (-200474, "DAQmxErrorOperationTimedOut"),
    (-200221, "DAQmxErrorTimeoutExceeded"),
    (-200479, "DAQmxErrorCanNotPerformOpWhileTaskRunning"),
    (-200010, "DAQmxErrorInputFIFOOverflow"),
    (-200361, "DAQmxErrorInputFIFOOverflow2"),
    (-200019, "DAQmxErrorADCOverrun"),
    (-200016, "DAQmxErrorOutputFIFOUnderflow"),
    (-200621, "DAQmxErrorOutputFIFOUnderflow2"),
    (-200018, "DAQmxErrorDACUnderflow"),
    (-200022, "DAQmxErrorResourceAlreadyReserved"),
    (-50103, "DAQmxErrorPALResourceReserved"),
    (-200462, "DAQmxErrorOutputBufferEmpty"),
    (
        -200802,
        "DAQmxErrorCannotWriteNotStartedAutoStartFalseNotOnDemandBufSizeZero",
    ),
    (-200604, "DAQmxErrorNULLPtr"),
];

/// The header's name of a DAQmx error code, when bfpscope knows it.
pub fn error_name(code: i32) -> Option<&'static str> {
    ERROR_NAMES
        .iter()
        .find(|(c, _)| *c == code)
        .map(|(_, n)| *n)
}

pub type CreateTask =
    unsafe extern "system" fn(task_name: *const c_char, task_handle: *mut TaskHandle) -> i32;
pub type TaskFn = unsafe extern "system" fn(task_handle: TaskHandle) -> i32;
pub type CreateAiVoltageChan = unsafe extern "system" fn(
    task_handle: TaskHandle,
    physical_channel: *const c_char,
    name_to_assign_to_channel: *const c_char,
    terminal_config: i32,
    min_val: f64,
    max_val: f64,
    units: i32,
    custom_scale_name: *const c_char,
) -> i32;
pub type CreateAoVoltageChan = unsafe extern "system" fn(
    task_handle: TaskHandle,
    physical_channel: *const c_char,
    name_to_assign_to_channel: *const c_char,
    min_val: f64,
    max_val: f64,
    units: i32,
    custom_scale_name: *const c_char,
) -> i32;
pub type CfgSampClkTiming = unsafe extern "system" fn(
    task_handle: TaskHandle,
    source: *const c_char,
    rate: f64,
    active_edge: i32,
    sample_mode: i32,
    samps_per_chan: u64,
) -> i32;
pub type CfgDigEdgeStartTrig = unsafe extern "system" fn(
    task_handle: TaskHandle,
    trigger_source: *const c_char,
    trigger_edge: i32,
) -> i32;
pub type ReadAnalogF64 = unsafe extern "system" fn(
    task_handle: TaskHandle,
    num_samps_per_chan: i32,
    timeout: f64,
    fill_mode: Bool32,
    read_array: *mut f64,
    array_size_in_samps: u32,
    samps_per_chan_read: *mut i32,
    reserved: *mut Bool32,
) -> i32;
pub type WriteAnalogF64 = unsafe extern "system" fn(
    task_handle: TaskHandle,
    num_samps_per_chan: i32,
    auto_start: Bool32,
    timeout: f64,
    data_layout: Bool32,
    write_array: *const f64,
    samps_per_chan_written: *mut i32,
    reserved: *mut Bool32,
) -> i32;
pub type WriteAnalogScalarF64 = unsafe extern "system" fn(
    task_handle: TaskHandle,
    auto_start: Bool32,
    timeout: f64,
    value: f64,
    reserved: *mut Bool32,
) -> i32;
pub type GetExtendedErrorInfo =
    unsafe extern "system" fn(error_string: *mut c_char, buffer_size: u32) -> i32;
pub type GetErrorString =
    unsafe extern "system" fn(error_code: i32, error_string: *mut c_char, buffer_size: u32) -> i32;
pub type CfgInputBuffer =
    unsafe extern "system" fn(task_handle: TaskHandle, num_samps_per_chan: u32) -> i32;
pub type GetDevProductType =
    unsafe extern "system" fn(device: *const c_char, data: *mut c_char, buffer_size: u32) -> i32;
pub type GetDevSerialNum = unsafe extern "system" fn(device: *const c_char, data: *mut u32) -> i32;
pub type SetWriteRegenMode = unsafe extern "system" fn(task_handle: TaskHandle, data: i32) -> i32;
/// `int32 DAQmxSetReadWaitMode(TaskHandle taskHandle, int32 data);`
pub type SetReadWaitMode = unsafe extern "system" fn(task_handle: TaskHandle, data: i32) -> i32;
/// `int32 DAQmxGetWriteSpaceAvail(TaskHandle taskHandle, uInt32 *data);`
pub type GetWriteSpaceAvail =
    unsafe extern "system" fn(task_handle: TaskHandle, data: *mut u32) -> i32;

/// Where NI-DAQmx is looked for.
pub const SPEC: LibrarySpec = LibrarySpec {
    what: "NI-DAQmx",
    config_key: "qpd.library",
    env_var: "BFPSCOPE_NIDAQMX",
    #[cfg(windows)]
    names: &["nicaiu.dll"],
    #[cfg(not(windows))]
    names: &["libnidaqmx.so", "libnidaqmx.so.1"],
    #[cfg(windows)]
    paths: &["C:\\Windows\\System32\\nicaiu.dll"],
    #[cfg(not(windows))]
    paths: &[
        "/usr/lib/x86_64-linux-gnu/libnidaqmx.so",
        "/usr/lib/x86_64-linux-gnu/libnidaqmx.so.1",
        "/usr/local/natinst/nidaqmx/lib/libnidaqmx.so",
        "/usr/lib/libnidaqmx.so",
    ],
};

vendor_library! {
    /// The loaded library and its functions. The pointers stay valid while `_lib` lives.
    pub struct NiDaqmx from SPEC {
        required {
            create_task: CreateTask = "DAQmxCreateTask",
            start_task: TaskFn = "DAQmxStartTask",
            stop_task: TaskFn = "DAQmxStopTask",
            clear_task: TaskFn = "DAQmxClearTask",
            create_ai_voltage_chan: CreateAiVoltageChan = "DAQmxCreateAIVoltageChan",
            create_ao_voltage_chan: CreateAoVoltageChan = "DAQmxCreateAOVoltageChan",
            cfg_samp_clk_timing: CfgSampClkTiming = "DAQmxCfgSampClkTiming",
            cfg_dig_edge_start_trig: CfgDigEdgeStartTrig = "DAQmxCfgDigEdgeStartTrig",
            read_analog_f64: ReadAnalogF64 = "DAQmxReadAnalogF64",
            write_analog_f64: WriteAnalogF64 = "DAQmxWriteAnalogF64",
            write_analog_scalar_f64: WriteAnalogScalarF64 = "DAQmxWriteAnalogScalarF64",
            get_extended_error_info: GetExtendedErrorInfo = "DAQmxGetExtendedErrorInfo",
        }
        optional {
            get_error_string: GetErrorString = "DAQmxGetErrorString",
            cfg_input_buffer: CfgInputBuffer = "DAQmxCfgInputBuffer",
            get_dev_product_type: GetDevProductType = "DAQmxGetDevProductType",
            get_dev_serial_num: GetDevSerialNum = "DAQmxGetDevSerialNum",
            set_write_regen_mode: SetWriteRegenMode = "DAQmxSetWriteRegenMode",
            get_write_space_avail: GetWriteSpaceAvail = "DAQmxGetWriteSpaceAvail",
            set_read_wait_mode: SetReadWaitMode = "DAQmxSetReadWaitMode",
        }
    }
}

impl NiDaqmx {
    /// `DAQmxGetExtendedErrorInfo`: the library's text for the last error of this thread.
    pub fn extended_error_info(&self) -> String {
        let mut buf = vec![0 as c_char; 4096];
        // SAFETY: `int32 DAQmxGetExtendedErrorInfo(char errorString[], uInt32 bufferSize)`,
        // the buffer holds `bufferSize` chars.
        unsafe { (self.get_extended_error_info)(buf.as_mut_ptr(), buf.len() as u32) };
        c_buf_to_string(&buf)
    }

    /// `DAQmxGetErrorString` for `code` (empty when the library lacks it).
    pub fn error_string(&self, code: i32) -> String {
        let Some(f) = self.get_error_string else {
            return String::new();
        };
        let mut buf = vec![0 as c_char; 2048];
        // SAFETY: `int32 DAQmxGetErrorString(int32 errorCode, char errorString[], uInt32 bufferSize)`.
        unsafe { f(code, buf.as_mut_ptr(), buf.len() as u32) };
        c_buf_to_string(&buf)
    }
}

/// A C string in `buf` (up to the first NUL, or all of it), lossily as UTF-8, trimmed.
pub fn c_buf_to_string(buf: &[c_char]) -> String {
    let bytes: Vec<u8> = buf
        .iter()
        .take_while(|&&c| c != 0)
        .map(|&c| c as u8)
        .collect();
    String::from_utf8_lossy(&bytes).trim().to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn error_names_are_unique_and_negative() {
        for (i, (c, n)) in ERROR_NAMES.iter().enumerate() {
            assert!(*c < 0 && n.starts_with("DAQmxError"), "{c} {n}");
            assert!(
                ERROR_NAMES[i + 1..].iter().all(|(d, _)| d != c),
                "{c} twice"
            );
        }
        assert_eq!(
            error_name(-200284),
            Some("DAQmxErrorSamplesNotYetAvailable")
        );
        assert_eq!(
            error_name(-200279),
            Some("DAQmxErrorSamplesNoLongerAvailable")
        );
        assert_eq!(error_name(1), None);
    }

    #[test]
    fn c_strings_stop_at_nul() {
        let b: Vec<c_char> = b"abc \0def".iter().map(|&b| b as c_char).collect();
        assert_eq!(c_buf_to_string(&b), "abc");
        let b: Vec<c_char> = b"xyz".iter().map(|&b| b as c_char).collect();
        assert_eq!(c_buf_to_string(&b), "xyz");
    }
}
