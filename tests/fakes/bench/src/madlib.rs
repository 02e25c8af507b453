//! Madlib, the Nano-Drive's C library, as declared in `Madlib.h` (Mad City Labs, BSD licence;
//! the copy published with Micro-Manager's MCL_NanoDrive adapter and the fuller one shipped
//! with MCL's Python/Matlab examples, June 2022). C types: `int` = i32, `unsigned int` = u32,
//! `short` = i16, `double` = f64, Madlib's `bool` = `unsigned char` (u8).
//!
//! One Nano-Drive is attached (unless the `no_stage` fault says otherwise). A handle is
//! "held" by this process from `MCL_InitHandle` / `MCL_GrabHandle` / `MCL_GrabAllHandles` until
//! `MCL_ReleaseHandle` / `MCL_ReleaseAllHandles`; a released or never-issued handle gets
//! `MCL_INVALID_HANDLE` (−8), and functions returning `double` return the code as a double,
//! as Madlib's do. Axes are 1 (x), 2 (y), 3 (z); 4 (AUX) and others get `MCL_INVALID_AXIS`.
//!
//! Positions outside [0, calibrated range] in `MCL_SingleWriteN`: Madlib's documents at hand
//! do not say whether the library clamps or refuses; the fake takes the safer reading and
//! refuses with `MCL_ARGUMENT_ERROR` (−6), without moving. The 16-bit Nano-Drive's waveform
//! limits (1–10000 points, 1/30–5 ms per point) are from MCL's documented wrapper texts.

use crate::errors::*;
use crate::{guard, now, sleep_until, with_bench, Bench};
use std::os::raw::{c_double, c_int, c_short, c_uchar, c_uint};

/// `struct ProductInformation` of Madlib.h, `#pragma pack(push, 1)`: 11 bytes.
#[repr(C, packed)]
#[derive(Debug, Clone, Copy, Default)]
pub struct ProductInformation {
    pub axis_bitmap: u8,
    pub adc_resolution: i16,
    pub dac_resolution: i16,
    pub product_id: i16,
    pub firmware_version: i16,
    pub firmware_profile: i16,
}

/// A waveform set up for one axis (`MCL_Setup_*WaveFormN`).
#[derive(Debug, Clone, Default)]
pub struct WaveSetup {
    pub read: Option<(u32, f64)>,
    pub load: Option<(Vec<f64>, f64)>,
}

/// A load waveform playing: axis, start, step (s), points; `next` is the first point not yet
/// applied.
#[derive(Debug, Clone)]
pub struct LoadWave {
    pub axis: usize,
    pub t0: f64,
    pub dt: f64,
    pub data: Vec<f64>,
    pub next: usize,
}

/// Madlib's side of the bench: handles and waveforms.
#[derive(Debug, Default)]
pub struct State {
    /// The handle by which this process holds the Nano-Drive.
    pub held: Option<i32>,
    next_handle: i32,
    /// Calls naming a handle so far (the `stage_unplug_after` fault counts them).
    pub calls: u64,
    pub unplugged: bool,
    pub waves: [WaveSetup; 3],
    pub playing: Vec<LoadWave>,
}

impl State {
    fn attached(&self, b_no_stage: bool) -> bool {
        !b_no_stage && !self.unplugged
    }
}

fn attached(b: &Bench) -> bool {
    b.mcl.attached(b.cfg.faults.no_stage)
}

/// Grab the Nano-Drive if it is attached and not held: its new handle, else 0.
fn grab(b: &mut Bench) -> i32 {
    if !attached(b) || b.mcl.held.is_some() {
        return 0;
    }
    b.mcl.next_handle += 1;
    let h = b.mcl.next_handle;
    b.mcl.held = Some(h);
    h
}

/// Check `handle` (and count the call for the unplug fault): `Err(code)` if it is not held
/// or the device is gone.
fn check(b: &mut Bench, handle: c_int) -> Result<(), i32> {
    if b.mcl.held != Some(handle) {
        return Err(MCL_INVALID_HANDLE);
    }
    if let Some(n) = b.cfg.faults.stage_unplug_after {
        if b.mcl.calls >= n {
            b.mcl.unplugged = true;
        }
    }
    b.mcl.calls += 1;
    if !attached(b) {
        return Err(MCL_DEV_NOT_ATTACHED);
    }
    Ok(())
}

fn axis_index(axis: c_uint) -> Result<usize, i32> {
    match axis {
        1..=3 => Ok(axis as usize - 1),
        _ => Err(MCL_INVALID_AXIS),
    }
}

fn logged<R: std::fmt::Debug>(b: &mut Bench, call: String, r: R) -> R {
    b.log(format!("{call} -> {r:?}"));
    r
}

// ---------------------------------------------------------------- library and handles

#[no_mangle]
pub extern "C" fn MCL_InitLibrary() -> c_uchar {
    guard(0, || {
        with_bench(|b| logged(b, "MCL_InitLibrary()".into(), 1))
    })
}

#[no_mangle]
pub extern "C" fn MCL_ReleaseLibrary() {
    guard((), || {
        with_bench(|b| {
            b.mcl.held = None;
            b.log("MCL_ReleaseLibrary() -> ()".into());
        })
    })
}

/// # Safety
/// `version` and `revision` are NULL or point to a `short` each.
#[no_mangle]
pub unsafe extern "C" fn MCL_DLLVersion(version: *mut c_short, revision: *mut c_short) {
    guard((), || {
        if !version.is_null() {
            *version = 2;
        }
        if !revision.is_null() {
            *revision = 0;
        }
        with_bench(|b| b.log("MCL_DLLVersion() -> (2, 0)".into()));
    })
}

#[no_mangle]
pub extern "C" fn MCL_CorrectDriverVersion() -> c_uchar {
    guard(0, || {
        with_bench(|b| logged(b, "MCL_CorrectDriverVersion()".into(), 1))
    })
}

#[no_mangle]
pub extern "C" fn MCL_InitHandle() -> c_int {
    guard(0, || {
        with_bench(|b| {
            let h = grab(b);
            logged(b, "MCL_InitHandle()".into(), h)
        })
    })
}

#[no_mangle]
pub extern "C" fn MCL_InitHandleOrGetExisting() -> c_int {
    guard(0, || {
        with_bench(|b| {
            let h = match b.mcl.held {
                Some(h) if attached(b) => h,
                _ => grab(b),
            };
            logged(b, "MCL_InitHandleOrGetExisting()".into(), h)
        })
    })
}

#[no_mangle]
pub extern "C" fn MCL_GrabHandle(device: c_short) -> c_int {
    guard(0, || {
        with_bench(|b| {
            let h = if device == crate::stage::PRODUCT_ID {
                grab(b)
            } else {
                0
            };
            logged(b, format!("MCL_GrabHandle(device={device:#06x})"), h)
        })
    })
}

#[no_mangle]
pub extern "C" fn MCL_GrabHandleOrGetExisting(device: c_short) -> c_int {
    guard(0, || {
        with_bench(|b| {
            let h = if device != crate::stage::PRODUCT_ID {
                0
            } else {
                match b.mcl.held {
                    Some(h) if attached(b) => h,
                    _ => grab(b),
                }
            };
            logged(
                b,
                format!("MCL_GrabHandleOrGetExisting(device={device:#06x})"),
                h,
            )
        })
    })
}

#[no_mangle]
pub extern "C" fn MCL_GrabAllHandles() -> c_int {
    guard(0, || {
        with_bench(|b| {
            grab(b);
            let n = i32::from(b.mcl.held.is_some() && attached(b));
            logged(b, "MCL_GrabAllHandles()".into(), n)
        })
    })
}

/// # Safety
/// `handles` is NULL or points to `size` ints.
#[no_mangle]
pub unsafe extern "C" fn MCL_GetAllHandles(handles: *mut c_int, size: c_int) -> c_int {
    guard(0, || {
        with_bench(|b| {
            let mut n = 0;
            if let Some(h) = b.mcl.held {
                if size >= 1 && !handles.is_null() {
                    *handles = h;
                    n = 1;
                }
            }
            logged(b, format!("MCL_GetAllHandles(size={size})"), n)
        })
    })
}

#[no_mangle]
pub extern "C" fn MCL_NumberOfCurrentHandles() -> c_int {
    guard(0, || {
        with_bench(|b| {
            let n = i32::from(b.mcl.held.is_some());
            logged(b, "MCL_NumberOfCurrentHandles()".into(), n)
        })
    })
}

#[no_mangle]
pub extern "C" fn MCL_GetHandleBySerial(serial: c_short) -> c_int {
    guard(0, || {
        with_bench(|b| {
            let h = match b.mcl.held {
                Some(h) if i32::from(serial) == b.stage.serial => h,
                _ => 0,
            };
            logged(b, format!("MCL_GetHandleBySerial(serial={serial})"), h)
        })
    })
}

#[no_mangle]
pub extern "C" fn MCL_ReleaseHandle(handle: c_int) {
    guard((), || {
        with_bench(|b| {
            let released = b.mcl.held == Some(handle);
            if released {
                b.mcl.held = None;
            }
            b.log(format!(
                "MCL_ReleaseHandle(handle={handle}) -> () [{}]",
                if released { "released" } else { "not held" }
            ));
        })
    })
}

#[no_mangle]
pub extern "C" fn MCL_ReleaseAllHandles() {
    guard((), || {
        with_bench(|b| {
            b.mcl.held = None;
            b.log("MCL_ReleaseAllHandles() -> ()".into());
        })
    })
}

// ---------------------------------------------------------------- motion

fn write_n(b: &mut Bench, position: f64, axis: c_uint, handle: c_int) -> i32 {
    let t = now();
    crate::daqmx::sync(b, t);
    if let Err(c) = check(b, handle) {
        return c;
    }
    let i = match axis_index(axis) {
        Ok(i) => i,
        Err(c) => return c,
    };
    let range = b.stage.axes[i].range;
    if !(position.is_finite() && (0.0..=range).contains(&position)) {
        return MCL_ARGUMENT_ERROR;
    }
    b.stage.command(i, t, position);
    MCL_SUCCESS
}

fn read_n(b: &mut Bench, axis: c_uint, handle: c_int) -> f64 {
    let t = now();
    crate::daqmx::sync(b, t);
    if let Err(c) = check(b, handle) {
        return c as f64;
    }
    match axis_index(axis) {
        Ok(i) => b.stage.read(i, t),
        Err(c) => c as f64,
    }
}

/// The USB round trip of a single read or write (setting `usb_ms`): the call returns that
/// long after it was made (busy-waiting, as a driver waiting on the bus does; a sleep's wake-up
/// on a busy host would add milliseconds a USB transfer does not have).
fn usb_round_trip(t0: f64, usb_s: f64) {
    while usb_s > 0.0 && now() < t0 + usb_s {
        std::hint::spin_loop();
    }
}

#[no_mangle]
pub extern "C" fn MCL_SingleWriteN(position: c_double, axis: c_uint, handle: c_int) -> c_int {
    guard(MCL_GENERAL_ERROR, || {
        let t0 = now();
        let (r, usb_s) = with_bench(|b| {
            let r = write_n(b, position, axis, handle);
            let r = logged(
                b,
                format!("MCL_SingleWriteN(position={position}, axis={axis}, handle={handle})"),
                r,
            );
            (r, b.cfg.usb_s)
        });
        usb_round_trip(t0, usb_s);
        r
    })
}

#[no_mangle]
pub extern "C" fn MCL_SingleReadN(axis: c_uint, handle: c_int) -> c_double {
    guard(MCL_GENERAL_ERROR as f64, || {
        let t0 = now();
        let (r, usb_s) = with_bench(|b| {
            let r = read_n(b, axis, handle);
            let r = logged(
                b,
                format!("MCL_SingleReadN(axis={axis}, handle={handle})"),
                r,
            );
            (r, b.cfg.usb_s)
        });
        usb_round_trip(t0, usb_s);
        r
    })
}

#[no_mangle]
pub extern "C" fn MCL_SingleWriteZ(position: c_double, handle: c_int) -> c_int {
    guard(MCL_GENERAL_ERROR, || {
        with_bench(|b| {
            let r = write_n(b, position, 3, handle);
            logged(
                b,
                format!("MCL_SingleWriteZ(position={position}, handle={handle})"),
                r,
            )
        })
    })
}

#[no_mangle]
pub extern "C" fn MCL_SingleReadZ(handle: c_int) -> c_double {
    guard(MCL_GENERAL_ERROR as f64, || {
        with_bench(|b| {
            let r = read_n(b, 3, handle);
            logged(b, format!("MCL_SingleReadZ(handle={handle})"), r)
        })
    })
}

#[no_mangle]
pub extern "C" fn MCL_MonitorN(position: c_double, axis: c_uint, handle: c_int) -> c_double {
    guard(MCL_GENERAL_ERROR as f64, || {
        with_bench(|b| {
            let w = write_n(b, position, axis, handle);
            let r = if w != MCL_SUCCESS {
                w as f64
            } else {
                let i = axis as usize - 1;
                b.stage.read(i, now())
            };
            logged(
                b,
                format!("MCL_MonitorN(position={position}, axis={axis}, handle={handle})"),
                r,
            )
        })
    })
}

#[no_mangle]
pub extern "C" fn MCL_MonitorZ(position: c_double, handle: c_int) -> c_double {
    MCL_MonitorN(position, 3, handle)
}

// ---------------------------------------------------------------- device information

#[no_mangle]
pub extern "C" fn MCL_GetCalibration(axis: c_uint, handle: c_int) -> c_double {
    guard(MCL_GENERAL_ERROR as f64, || {
        with_bench(|b| {
            let r = match check(b, handle).and_then(|_| axis_index(axis)) {
                Ok(i) => b.stage.axes[i].range,
                Err(c) => c as f64,
            };
            logged(
                b,
                format!("MCL_GetCalibration(axis={axis}, handle={handle})"),
                r,
            )
        })
    })
}

#[no_mangle]
pub extern "C" fn MCL_GetSerialNumber(handle: c_int) -> c_int {
    guard(MCL_GENERAL_ERROR, || {
        with_bench(|b| {
            let r = match check(b, handle) {
                Ok(()) => b.stage.serial,
                Err(c) => c,
            };
            logged(b, format!("MCL_GetSerialNumber(handle={handle})"), r)
        })
    })
}

/// # Safety
/// `pi` is NULL or points to a `struct ProductInformation` (11 bytes, packed).
#[no_mangle]
pub unsafe extern "C" fn MCL_GetProductInfo(pi: *mut ProductInformation, handle: c_int) -> c_int {
    guard(MCL_GENERAL_ERROR, || {
        with_bench(|b| {
            let r = match check(b, handle) {
                Err(c) => c,
                Ok(()) if pi.is_null() => MCL_ARGUMENT_ERROR,
                Ok(()) => {
                    std::ptr::write_unaligned(
                        pi,
                        ProductInformation {
                            axis_bitmap: 0x07,
                            adc_resolution: 16,
                            dac_resolution: 16,
                            product_id: crate::stage::PRODUCT_ID,
                            firmware_version: crate::stage::FIRMWARE_VERSION,
                            firmware_profile: crate::stage::FIRMWARE_PROFILE,
                        },
                    );
                    MCL_SUCCESS
                }
            };
            logged(b, format!("MCL_GetProductInfo(handle={handle})"), r)
        })
    })
}

/// # Safety
/// `version` and `profile` are NULL or point to a `short` each.
#[no_mangle]
pub unsafe extern "C" fn MCL_GetFirmwareVersion(
    version: *mut c_short,
    profile: *mut c_short,
    handle: c_int,
) -> c_int {
    guard(MCL_GENERAL_ERROR, || {
        with_bench(|b| {
            let r = match check(b, handle) {
                Err(c) => c,
                Ok(()) if version.is_null() || profile.is_null() => MCL_ARGUMENT_ERROR,
                Ok(()) => {
                    *version = crate::stage::FIRMWARE_VERSION;
                    *profile = crate::stage::FIRMWARE_PROFILE;
                    MCL_SUCCESS
                }
            };
            logged(b, format!("MCL_GetFirmwareVersion(handle={handle})"), r)
        })
    })
}

#[no_mangle]
pub extern "C" fn MCL_PrintDeviceInfo(handle: c_int) {
    guard((), || {
        let text = with_bench(|b| {
            let r = check(b, handle);
            b.log(format!("MCL_PrintDeviceInfo(handle={handle}) -> ()"));
            r.ok().map(|_| {
                format!(
                    "Nano-Drive (fake) product id {:#06x}, serial {}, firmware {} profile {:#06x}, ranges {} / {} / {} µm",
                    crate::stage::PRODUCT_ID,
                    b.stage.serial,
                    crate::stage::FIRMWARE_VERSION,
                    crate::stage::FIRMWARE_PROFILE,
                    b.stage.axes[0].range,
                    b.stage.axes[1].range,
                    b.stage.axes[2].range
                )
            })
        });
        if let Some(t) = text {
            println!("{t}");
        }
    })
}

/// Waits `milliseconds`, then tells whether the Nano-Drive is attached (Madlib's contract).
#[no_mangle]
pub extern "C" fn MCL_DeviceAttached(milliseconds: c_int, handle: c_int) -> c_uchar {
    guard(0, || {
        let t_end = now() + f64::from(milliseconds.max(0)) / 1e3;
        sleep_until(t_end);
        with_bench(|b| {
            let r = u8::from(check(b, handle).is_ok());
            logged(
                b,
                format!("MCL_DeviceAttached(milliseconds={milliseconds}, handle={handle})"),
                r,
            )
        })
    })
}

/// # Safety
/// The three pointers are NULL or point to a `double` each.
#[no_mangle]
pub unsafe extern "C" fn MCL_GetCommandedPosition(
    x: *mut c_double,
    y: *mut c_double,
    z: *mut c_double,
    handle: c_int,
) -> c_int {
    guard(MCL_GENERAL_ERROR, || {
        with_bench(|b| {
            let r = match check(b, handle) {
                Err(c) => c,
                Ok(()) if x.is_null() || y.is_null() || z.is_null() => MCL_ARGUMENT_ERROR,
                Ok(()) => {
                    *x = b.stage.axes[0].usb;
                    *y = b.stage.axes[1].usb;
                    *z = b.stage.axes[2].usb;
                    MCL_SUCCESS
                }
            };
            logged(b, format!("MCL_GetCommandedPosition(handle={handle})"), r)
        })
    })
}

// ---------------------------------------------------------------- waveforms

const WAVE_MAX_POINTS: u32 = 10_000;
const WAVE_MIN_MS: f64 = 1.0 / 30.0;
const WAVE_MAX_MS: f64 = 5.0;

fn wave_args(axis: c_uint, points: c_uint, ms: f64) -> Result<usize, i32> {
    let i = axis_index(axis)?;
    let points_ok = (1..=WAVE_MAX_POINTS).contains(&points);
    let ms_ok = ms.is_finite() && (WAVE_MIN_MS - 1e-12..=WAVE_MAX_MS).contains(&ms);
    if !(points_ok && ms_ok) {
        return Err(MCL_ARGUMENT_ERROR);
    }
    Ok(i)
}

fn setup_read(b: &mut Bench, axis: c_uint, points: c_uint, ms: f64, handle: c_int) -> i32 {
    if let Err(c) = check(b, handle) {
        return c;
    }
    match wave_args(axis, points, ms) {
        Ok(i) => {
            b.mcl.waves[i].read = Some((points, ms));
            MCL_SUCCESS
        }
        Err(c) => c,
    }
}

/// # Safety
/// `wave` points to `points` doubles.
unsafe fn setup_load(
    b: &mut Bench,
    axis: c_uint,
    points: c_uint,
    ms: f64,
    wave: *const c_double,
    handle: c_int,
) -> i32 {
    if let Err(c) = check(b, handle) {
        return c;
    }
    let i = match wave_args(axis, points, ms) {
        Ok(i) => i,
        Err(c) => return c,
    };
    if wave.is_null() {
        return MCL_ARGUMENT_ERROR;
    }
    let data = std::slice::from_raw_parts(wave, points as usize).to_vec();
    let range = b.stage.axes[i].range;
    if data
        .iter()
        .any(|p| !(p.is_finite() && (0.0..=range).contains(p)))
    {
        return MCL_ARGUMENT_ERROR;
    }
    b.mcl.waves[i].load = Some((data, ms));
    MCL_SUCCESS
}

/// Start the set-up load waveform of axis `i` at `t0`.
fn start_load(b: &mut Bench, i: usize, t0: f64) -> Result<(), i32> {
    let (data, ms) = b.mcl.waves[i].load.clone().ok_or(MCL_USAGE_ERROR)?;
    b.mcl.playing.retain(|w| w.axis != i);
    b.mcl.playing.push(LoadWave {
        axis: i,
        t0,
        dt: ms / 1e3,
        data,
        next: 0,
    });
    Ok(())
}

/// Sample the sensor of axis `i` at `t0 + k·dt`, k < n, waiting until the last sample's time.
///
/// # Safety
/// `out` points to `n` doubles.
unsafe fn sample_read(i: usize, n: usize, dt: f64, t0: f64, out: *mut c_double) {
    sleep_until(t0 + n as f64 * dt);
    with_bench(|b| {
        crate::daqmx::sync(b, now());
        for k in 0..n {
            *out.add(k) = b.stage.read(i, t0 + k as f64 * dt);
        }
    });
}

#[no_mangle]
pub extern "C" fn MCL_Setup_ReadWaveFormN(
    axis: c_uint,
    data_points: c_uint,
    milliseconds: c_double,
    handle: c_int,
) -> c_int {
    guard(MCL_GENERAL_ERROR, || {
        with_bench(|b| {
            let r = setup_read(b, axis, data_points, milliseconds, handle);
            logged(
                b,
                format!("MCL_Setup_ReadWaveFormN(axis={axis}, DataPoints={data_points}, milliseconds={milliseconds}, handle={handle})"),
                r,
            )
        })
    })
}

/// # Safety
/// `waveform` points to `data_points` doubles.
#[no_mangle]
pub unsafe extern "C" fn MCL_Trigger_ReadWaveFormN(
    axis: c_uint,
    data_points: c_uint,
    waveform: *mut c_double,
    handle: c_int,
) -> c_int {
    guard(MCL_GENERAL_ERROR, || {
        let prep = with_bench(|b| {
            let r = (|| {
                check(b, handle)?;
                let i = axis_index(axis)?;
                let (n, ms) = b.mcl.waves[i].read.ok_or(MCL_USAGE_ERROR)?;
                if n != data_points || waveform.is_null() {
                    return Err(MCL_ARGUMENT_ERROR);
                }
                Ok((i, n as usize, ms / 1e3, now()))
            })();
            b.log(format!(
                "MCL_Trigger_ReadWaveFormN(axis={axis}, DataPoints={data_points}, handle={handle}) -> {}",
                r.err().unwrap_or(0)
            ));
            r
        });
        match prep {
            Err(c) => c,
            Ok((i, n, dt, t0)) => {
                sample_read(i, n, dt, t0, waveform);
                MCL_SUCCESS
            }
        }
    })
}

/// # Safety
/// `waveform` points to `data_points` doubles.
#[no_mangle]
pub unsafe extern "C" fn MCL_ReadWaveFormN(
    axis: c_uint,
    data_points: c_uint,
    milliseconds: c_double,
    waveform: *mut c_double,
    handle: c_int,
) -> c_int {
    guard(MCL_GENERAL_ERROR, || {
        let prep = with_bench(|b| {
            let r = (|| {
                check(b, handle)?;
                let i = wave_args(axis, data_points, milliseconds)?;
                if waveform.is_null() {
                    return Err(MCL_ARGUMENT_ERROR);
                }
                Ok((i, data_points as usize, milliseconds / 1e3, now()))
            })();
            b.log(format!(
                "MCL_ReadWaveFormN(axis={axis}, DataPoints={data_points}, milliseconds={milliseconds}, handle={handle}) -> {}",
                r.err().unwrap_or(0)
            ));
            r
        });
        match prep {
            Err(c) => c,
            Ok((i, n, dt, t0)) => {
                sample_read(i, n, dt, t0, waveform);
                MCL_SUCCESS
            }
        }
    })
}

/// # Safety
/// `waveform` points to `data_points` doubles.
#[no_mangle]
pub unsafe extern "C" fn MCL_Setup_LoadWaveFormN(
    axis: c_uint,
    data_points: c_uint,
    milliseconds: c_double,
    waveform: *const c_double,
    handle: c_int,
) -> c_int {
    guard(MCL_GENERAL_ERROR, || {
        with_bench(|b| {
            let r = setup_load(b, axis, data_points, milliseconds, waveform, handle);
            logged(
                b,
                format!("MCL_Setup_LoadWaveFormN(axis={axis}, DataPoints={data_points}, milliseconds={milliseconds}, handle={handle})"),
                r,
            )
        })
    })
}

#[no_mangle]
pub extern "C" fn MCL_Trigger_LoadWaveFormN(axis: c_uint, handle: c_int) -> c_int {
    guard(MCL_GENERAL_ERROR, || {
        with_bench(|b| {
            let t = now();
            crate::daqmx::sync(b, t);
            let r = (|| {
                check(b, handle)?;
                let i = axis_index(axis)?;
                start_load(b, i, t)
            })()
            .err()
            .unwrap_or(MCL_SUCCESS);
            logged(
                b,
                format!("MCL_Trigger_LoadWaveFormN(axis={axis}, handle={handle})"),
                r,
            )
        })
    })
}

/// # Safety
/// `waveform` points to `data_points` doubles.
#[no_mangle]
pub unsafe extern "C" fn MCL_LoadWaveFormN(
    axis: c_uint,
    data_points: c_uint,
    milliseconds: c_double,
    waveform: *const c_double,
    handle: c_int,
) -> c_int {
    guard(MCL_GENERAL_ERROR, || {
        let r = with_bench(|b| {
            let t = now();
            crate::daqmx::sync(b, t);
            let r = match setup_load(b, axis, data_points, milliseconds, waveform, handle) {
                MCL_SUCCESS => start_load(b, axis as usize - 1, t)
                    .map(|_| t + f64::from(data_points) * milliseconds / 1e3),
                c => Err(c),
            };
            b.log(format!(
                "MCL_LoadWaveFormN(axis={axis}, DataPoints={data_points}, milliseconds={milliseconds}, handle={handle}) -> {}",
                r.err().unwrap_or(0)
            ));
            r
        });
        match r {
            Ok(t_end) => {
                sleep_until(t_end);
                MCL_SUCCESS
            }
            Err(c) => c,
        }
    })
}

/// # Safety
/// `waveform` points to `data_points` doubles.
#[no_mangle]
pub unsafe extern "C" fn MCL_TriggerWaveformAcquisition(
    axis: c_uint,
    data_points: c_uint,
    waveform: *mut c_double,
    handle: c_int,
) -> c_int {
    guard(MCL_GENERAL_ERROR, || {
        let prep = with_bench(|b| {
            let t = now();
            crate::daqmx::sync(b, t);
            let r = (|| {
                check(b, handle)?;
                let i = axis_index(axis)?;
                let (n, ms) = b.mcl.waves[i].read.ok_or(MCL_USAGE_ERROR)?;
                if n != data_points || waveform.is_null() {
                    return Err(MCL_ARGUMENT_ERROR);
                }
                start_load(b, i, t)?;
                Ok((i, n as usize, ms / 1e3, t))
            })();
            b.log(format!(
                "MCL_TriggerWaveformAcquisition(axis={axis}, DataPoints={data_points}, handle={handle}) -> {}",
                r.err().unwrap_or(0)
            ));
            r
        });
        match prep {
            Err(c) => c,
            Ok((i, n, dt, t0)) => {
                sample_read(i, n, dt, t0, waveform);
                MCL_SUCCESS
            }
        }
    })
}
