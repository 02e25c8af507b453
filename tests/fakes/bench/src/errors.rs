//! Vendor error codes and texts.
//!
//! Madlib's codes are `Madlib.h`'s `#define`s. NI-DAQmx's codes are `NIDAQmx.h`'s
//! `DAQmxError…` `#define`s; their texts are NI's published ones where a public copy was found
//! (NI-DAQmx Base 2.1's README list of "errors … of the Windows version of NI-DAQmx", error
//! reports quoting the driver's message); the few written from memory say so below.

// ---- Madlib.h ----
pub const MCL_SUCCESS: i32 = 0;
pub const MCL_GENERAL_ERROR: i32 = -1;
pub const MCL_DEV_ERROR: i32 = -2;
pub const MCL_DEV_NOT_ATTACHED: i32 = -3;
pub const MCL_USAGE_ERROR: i32 = -4;
pub const MCL_DEV_NOT_READY: i32 = -5;
pub const MCL_ARGUMENT_ERROR: i32 = -6;
pub const MCL_INVALID_AXIS: i32 = -7;
pub const MCL_INVALID_HANDLE: i32 = -8;

// ---- NIDAQmx.h error codes ----
pub const SAMPLES_NOT_YET_AVAILABLE: i32 = -200284;
pub const SAMPLES_NO_LONGER_AVAILABLE: i32 = -200279;
pub const SAMPLES_WILL_NEVER_BE_AVAILABLE: i32 = -200278;
pub const INVALID_DEVICE_ID: i32 = -200220;
pub const INVALID_ATTRIBUTE_VALUE: i32 = -200077;
pub const PHYSICAL_CHAN_DOES_NOT_EXIST: i32 = -200170;
pub const INVALID_TASK: i32 = -200088;
pub const DUPLICATE_TASK: i32 = -200089;
pub const MIN_NOT_LESS_THAN_MAX: i32 = -200082;
pub const DEV_CANNOT_BE_ACCESSED: i32 = -201003;
pub const OPERATION_TIMED_OUT: i32 = -200474;
pub const NO_CHANS_IN_TASK: i32 = -200478;
pub const OP_WHILE_TASK_RUNNING: i32 = -200479;
pub const INVALID_PHYS_CHAN_TYPE: i32 = -200430;
pub const MULTI_CHAN_TYPES_IN_TASK: i32 = -200559;
pub const INVALID_AO_DATA_WRITE: i32 = -200561;
pub const WAIT_UNTIL_DONE_NOT_DONE: i32 = -200560;
pub const OUTPUT_BUFFER_EMPTY: i32 = -200462;
pub const READ_BUFFER_TOO_SMALL: i32 = -200229;
pub const NULL_PTR: i32 = -200604;
pub const READ_CHAN_TYPE_MISMATCH: i32 = -200525;
pub const WRITE_CHAN_TYPE_MISMATCH: i32 = -200526;
pub const WRITE_NUM_CHANS_MISMATCH: i32 = -200524;
pub const RESOURCE_RESERVED: i32 = -50103;
pub const ROUTE_SRC_NOT_FOUND: i32 = -89120;
pub const PHYS_CHAN_NOT_SPECIFIED: i32 = -200099;
pub const DUPLICATE_CHANNEL: i32 = -200489;
pub const NEGATIVE_WRITE_SAMPLE_NUMBER: i32 = -200287;
pub const ATTRIBUTE_NOT_SUPPORTED: i32 = -200452;
pub const GEN_STOPPED_TO_PREVENT_REGEN_OF_OLD_SAMPLES: i32 = -200290;
pub const SAMPLES_CAN_NOT_YET_BE_WRITTEN: i32 = -200292;

/// NI's text for a DAQmx status code (`DAQmxGetErrorString`).
pub fn daqmx_text(code: i32) -> &'static str {
    match code {
        0 => "",
        // NI-DAQmx Base 2.1 README (NI's list of NI-DAQmx errors)
        SAMPLES_NOT_YET_AVAILABLE => "Some or all of the samples requested have not yet been acquired.\nTo wait for the samples to become available use a longer read timeout or read later in your program. To make the samples available sooner, increase the sample rate. If your task uses a start trigger, make sure that your start trigger is configured correctly. It is also possible that you configured the task for external timing, and no clock was supplied. If this is the case, supply an external clock.",
        SAMPLES_WILL_NEVER_BE_AVAILABLE => "Attempted to read a sample beyond the final sample acquired. The acquisition has stopped, therefore the sample specified by the combination of position and offset will never be available.\nSpecify a position and offset which selects a sample up to, but not beyond, the final sample acquired. The final sample acquired can be determined by querying the total samples acquired after an acquisition has stopped.",
        INVALID_DEVICE_ID => "Device identifier is invalid.",
        INVALID_ATTRIBUTE_VALUE => "Requested value is not a supported value for this property. The property value may be invalid because it conflicts with another property.",
        PHYSICAL_CHAN_DOES_NOT_EXIST => "Physical channel specified does not exist on this device.\nRefer to the documentation for channels available on this device.",
        DUPLICATE_TASK => "Task name specified conflicts with an existing task name.",
        MIN_NOT_LESS_THAN_MAX => "Minimum is greater than or equal to the maximum.",
        OPERATION_TIMED_OUT => "Specified operation did not complete, because the specified timeout expired.",
        NO_CHANS_IN_TASK => "Specified operation cannot be performed when there are no channels in the task.",
        INVALID_PHYS_CHAN_TYPE => "I/O type of the physical channel does not match the I/O type required for the virtual channel you are creating.",
        MULTI_CHAN_TYPES_IN_TASK => "Task cannot contain a channel with the specified channel type, because the task already contains channels with a different channel type.  Create one task for each channel type.",
        INVALID_AO_DATA_WRITE => "Attempted writing analog data that is too large or too small.",
        WRITE_NUM_CHANS_MISMATCH => "Write cannot be performed, because the data does not contain data for all channels in the task.  When writing, supply data for all channels in the task Alternatively, modify the task to contain the same number of channels as the data written.",
        READ_CHAN_TYPE_MISMATCH => "Read cannot be performed because this version of DAQmx Read does not match the type of channels in the task.\nUse the version of DAQmx Read that corresponds to the channel type.",
        WRITE_CHAN_TYPE_MISMATCH => "Write cannot be performed because this version of DAQmx Write does not match the type of channels in the task.\nUse the version of DAQmx Write that corresponds to the channel type.",
        PHYS_CHAN_NOT_SPECIFIED => "Physical channel not specified.",
        DUPLICATE_CHANNEL => "Specified channel cannot be added to the task, because a channel with the same name is already in the task.",
        NEGATIVE_WRITE_SAMPLE_NUMBER => "Attempted to write to an invalid combination of position and offset. The position and offset specified a sample prior to the first sample generated (sample 0).  Make sure any negative write offset specified will select a valid sample when combined with the write position.",
        ATTRIBUTE_NOT_SUPPORTED => "Specified property is not supported by the device or is not applicable to the task.",
        ROUTE_SRC_NOT_FOUND => "Source terminal to be routed could not be found on the device.  Make sure the terminal name is valid for the specified device.",
        // quoted in error reports of the driver's message (open-ephys/GUI#396, PyDAQmx users)
        SAMPLES_NO_LONGER_AVAILABLE => "The application is not able to keep up with the hardware acquisition.\nIncreasing the buffer size, reading the data more frequently, or specifying a fixed number of samples to read instead of reading all available samples might correct the problem.",
        INVALID_TASK => "Task specified is invalid or does not exist.",
        // written from memory of NI's text (no public copy found to check against)
        GEN_STOPPED_TO_PREVENT_REGEN_OF_OLD_SAMPLES => "The generation has stopped to prevent the regeneration of old samples. Your application was unable to write samples to the background buffer fast enough to prevent old samples from being regenerated.\nTo avoid this error, you can do any of the following:\n1. Increase the size of the background buffer by configuring the buffer.\n2. Increase the number of samples you write each time you invoke a write operation.\n3. Write samples more often.\n4. Reduce the sample rate.",
        SAMPLES_CAN_NOT_YET_BE_WRITTEN => "Some or all of the samples to write could not be written to the buffer yet. More space will free up as samples currently in the buffer are generated.\nTo wait for more space to become available, use a longer write timeout. To make the space available sooner, increase the sample rate.",
        RESOURCE_RESERVED => "The specified resource is reserved. The operation could not be completed as specified.",
        // written from memory of NI's texts (no public copy found to check against)
        DEV_CANNOT_BE_ACCESSED => "Device cannot be accessed.\nPossible causes:\nDevice is no longer present in the system.\nDevice is not powered.\nDevice is powered, but was temporarily without power.\nDevice is damaged.\nEnsure the device is properly connected and powered. Turn the computer off and on again. If you suspect that the device is damaged, contact National Instruments at ni.com/support.",
        OP_WHILE_TASK_RUNNING => "Specified operation cannot be performed while the task is running.",
        WAIT_UNTIL_DONE_NOT_DONE => "Wait Until Done did not indicate all samples were acquired/generated within the specified timeout.",
        OUTPUT_BUFFER_EMPTY => "Generation cannot be started, because the output buffer is empty.\nWrite data before starting a buffered generation.",
        READ_BUFFER_TOO_SMALL => "Buffer is too small to fit read data.",
        NULL_PTR => "Required pointer argument is NULL.",
        _ => "Error code could not be found.",
    }
}

/// Madlib's meaning of its return codes (Madlib.h's names, in words).
pub fn mcl_text(code: i32) -> &'static str {
    match code {
        MCL_SUCCESS => "MCL_SUCCESS",
        MCL_GENERAL_ERROR => "MCL_GENERAL_ERROR",
        MCL_DEV_ERROR => "MCL_DEV_ERROR",
        MCL_DEV_NOT_ATTACHED => "MCL_DEV_NOT_ATTACHED",
        MCL_USAGE_ERROR => "MCL_USAGE_ERROR",
        MCL_DEV_NOT_READY => "MCL_DEV_NOT_READY",
        MCL_ARGUMENT_ERROR => "MCL_ARGUMENT_ERROR",
        MCL_INVALID_AXIS => "MCL_INVALID_AXIS",
        MCL_INVALID_HANDLE => "MCL_INVALID_HANDLE",
        _ => "unknown Madlib code",
    }
}
