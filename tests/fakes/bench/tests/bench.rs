//! The fake bench through its C interface, loaded with `libloading` as a driver loads the
//! vendors' libraries, with declarations written here from Madlib.h and NIDAQmx.h (not shared
//! with the fake's code nor with bfpscope's drivers).
//!
//! One process, one library instance: the tests share it, so each takes the lock and resets
//! the bench first.

use libloading::{Library, Symbol};
use std::ffi::{c_char, c_double, c_int, c_short, c_uchar, c_uint, c_void, CString};
use std::sync::{Mutex, MutexGuard, OnceLock};

// ---- Madlib.h
const MCL_SUCCESS: c_int = 0;
const MCL_DEV_NOT_ATTACHED: c_int = -3;
const MCL_ARGUMENT_ERROR: c_int = -6;
const MCL_INVALID_AXIS: c_int = -7;
const MCL_INVALID_HANDLE: c_int = -8;

#[repr(C, packed)]
#[derive(Default, Clone, Copy)]
struct ProductInformation {
    axis_bitmap: u8,
    adc_resolution: i16,
    dac_resolution: i16,
    product_id: i16,
    firmware_version: i16,
    firmware_profile: i16,
}

// ---- NIDAQmx.h (Linux x86_64: int32 = int, uInt32 = unsigned int)
type TaskHandle = *mut c_void;
const DAQMX_VAL_VOLTS: i32 = 10348;
const DAQMX_VAL_RISING: i32 = 10280;
const DAQMX_VAL_FINITE_SAMPS: i32 = 10178;
const DAQMX_VAL_CONT_SAMPS: i32 = 10123;
const DAQMX_VAL_GROUP_BY_CHANNEL: u32 = 0;
const DAQMX_VAL_GROUP_BY_SCAN_NUMBER: u32 = 1;
const DAQMX_VAL_DIFF: i32 = 10106;
const DAQMX_VAL_RSE: i32 = 10083;
const DAQMX_VAL_CFG_DEFAULT: i32 = -1;

fn lib_path() -> std::path::PathBuf {
    // the test runs from target/<profile>/deps/; `cargo build` puts the library in
    // target/<profile>/, a test build (the library built as a dependency) in deps/: the newer
    let exe = std::env::current_exe().unwrap();
    let deps = exe.parent().unwrap();
    let newest = [
        deps.join("libfakebench.so"),
        deps.parent().unwrap().join("libfakebench.so"),
    ]
    .into_iter()
    .filter_map(|p| Some((std::fs::metadata(&p).ok()?.modified().ok()?, p)))
    .max();
    newest
        .expect("libfakebench.so missing next to the test: build the workspace (cargo build)")
        .1
}

struct Fake {
    lib: Library,
}

fn fake() -> (MutexGuard<'static, ()>, &'static Fake) {
    static LOCK: Mutex<()> = Mutex::new(());
    static LIB: OnceLock<Fake> = OnceLock::new();
    let g = LOCK.lock().unwrap_or_else(|e| e.into_inner());
    let f = LIB.get_or_init(|| Fake {
        lib: unsafe { Library::new(lib_path()).unwrap() },
    });
    unsafe {
        let reset: Symbol<unsafe extern "C" fn() -> c_int> = f.lib.get(b"fakebench_reset").unwrap();
        assert_eq!(reset(), 0);
    }
    (g, f)
}

macro_rules! sym {
    ($f:expr, $name:literal, $t:ty) => {{
        let s: Symbol<$t> = unsafe { $f.lib.get($name.as_bytes()).unwrap() };
        s
    }};
}

impl Fake {
    fn set(&self, key: &str, value: &str) {
        let f = sym!(
            self,
            "fakebench_set",
            unsafe extern "C" fn(*const c_char, *const c_char) -> c_int
        );
        let (k, v) = (CString::new(key).unwrap(), CString::new(value).unwrap());
        assert_eq!(
            unsafe { f(k.as_ptr(), v.as_ptr()) },
            0,
            "fakebench_set {key}={value}"
        );
    }
    fn faults(&self, spec: &str) {
        let f = sym!(
            self,
            "fakebench_set_faults",
            unsafe extern "C" fn(*const c_char) -> c_int
        );
        let s = CString::new(spec).unwrap();
        assert_eq!(unsafe { f(s.as_ptr()) }, 0);
    }
    fn log(&self) -> String {
        let f = sym!(
            self,
            "fakebench_log",
            unsafe extern "C" fn(*mut c_char, usize) -> usize
        );
        let n = unsafe { f(std::ptr::null_mut(), 0) };
        let mut buf = vec![0u8; n];
        unsafe { f(buf.as_mut_ptr() as *mut c_char, n) };
        String::from_utf8_lossy(&buf[..n - 1]).into_owned()
    }
    fn position(&self, axis: c_int) -> f64 {
        let f = sym!(
            self,
            "fakebench_stage_position",
            unsafe extern "C" fn(c_int) -> c_double
        );
        unsafe { f(axis) }
    }
    fn ao_voltage(&self, ch: c_int) -> f64 {
        let f = sym!(
            self,
            "fakebench_ao_voltage",
            unsafe extern "C" fn(c_int) -> c_double
        );
        unsafe { f(ch) }
    }

    // Madlib
    fn init_handle(&self) -> c_int {
        let f = sym!(self, "MCL_InitHandle", unsafe extern "C" fn() -> c_int);
        unsafe { f() }
    }
    fn grab_all(&self) -> c_int {
        let f = sym!(self, "MCL_GrabAllHandles", unsafe extern "C" fn() -> c_int);
        unsafe { f() }
    }
    fn release(&self, h: c_int) {
        let f = sym!(self, "MCL_ReleaseHandle", unsafe extern "C" fn(c_int));
        unsafe { f(h) }
    }
    fn by_serial(&self, s: c_short) -> c_int {
        let f = sym!(
            self,
            "MCL_GetHandleBySerial",
            unsafe extern "C" fn(c_short) -> c_int
        );
        unsafe { f(s) }
    }
    fn write(&self, pos: f64, axis: c_uint, h: c_int) -> c_int {
        let f = sym!(
            self,
            "MCL_SingleWriteN",
            unsafe extern "C" fn(c_double, c_uint, c_int) -> c_int
        );
        unsafe { f(pos, axis, h) }
    }
    fn read(&self, axis: c_uint, h: c_int) -> f64 {
        let f = sym!(
            self,
            "MCL_SingleReadN",
            unsafe extern "C" fn(c_uint, c_int) -> c_double
        );
        unsafe { f(axis, h) }
    }
    fn calibration(&self, axis: c_uint, h: c_int) -> f64 {
        let f = sym!(
            self,
            "MCL_GetCalibration",
            unsafe extern "C" fn(c_uint, c_int) -> c_double
        );
        unsafe { f(axis, h) }
    }

    // NI-DAQmx
    fn create_task(&self) -> TaskHandle {
        let f = sym!(
            self,
            "DAQmxCreateTask",
            unsafe extern "C" fn(*const c_char, *mut TaskHandle) -> i32
        );
        let mut h: TaskHandle = std::ptr::null_mut();
        let name = CString::new("").unwrap();
        assert_eq!(unsafe { f(name.as_ptr(), &mut h) }, 0);
        h
    }
    fn ai_chan(&self, t: TaskHandle, phys: &str, term: i32, min: f64, max: f64) -> i32 {
        let f = sym!(
            self,
            "DAQmxCreateAIVoltageChan",
            unsafe extern "C" fn(
                TaskHandle,
                *const c_char,
                *const c_char,
                i32,
                f64,
                f64,
                i32,
                *const c_char,
            ) -> i32
        );
        let p = CString::new(phys).unwrap();
        let e = CString::new("").unwrap();
        unsafe {
            f(
                t,
                p.as_ptr(),
                e.as_ptr(),
                term,
                min,
                max,
                DAQMX_VAL_VOLTS,
                std::ptr::null(),
            )
        }
    }
    fn ao_chan(&self, t: TaskHandle, phys: &str) -> i32 {
        let f = sym!(
            self,
            "DAQmxCreateAOVoltageChan",
            unsafe extern "C" fn(
                TaskHandle,
                *const c_char,
                *const c_char,
                f64,
                f64,
                i32,
                *const c_char,
            ) -> i32
        );
        let p = CString::new(phys).unwrap();
        let e = CString::new("").unwrap();
        unsafe {
            f(
                t,
                p.as_ptr(),
                e.as_ptr(),
                -10.0,
                10.0,
                DAQMX_VAL_VOLTS,
                std::ptr::null(),
            )
        }
    }
    fn timing(&self, t: TaskHandle, src: &str, rate: f64, mode: i32, n: u64) -> i32 {
        let f = sym!(
            self,
            "DAQmxCfgSampClkTiming",
            unsafe extern "C" fn(TaskHandle, *const c_char, f64, i32, i32, u64) -> i32
        );
        let s = CString::new(src).unwrap();
        unsafe { f(t, s.as_ptr(), rate, DAQMX_VAL_RISING, mode, n) }
    }
    fn start_trigger(&self, t: TaskHandle, src: &str) -> i32 {
        let f = sym!(
            self,
            "DAQmxCfgDigEdgeStartTrig",
            unsafe extern "C" fn(TaskHandle, *const c_char, i32) -> i32
        );
        let s = CString::new(src).unwrap();
        unsafe { f(t, s.as_ptr(), DAQMX_VAL_RISING) }
    }
    fn start(&self, t: TaskHandle) -> i32 {
        let f = sym!(
            self,
            "DAQmxStartTask",
            unsafe extern "C" fn(TaskHandle) -> i32
        );
        unsafe { f(t) }
    }
    fn stop(&self, t: TaskHandle) -> i32 {
        let f = sym!(
            self,
            "DAQmxStopTask",
            unsafe extern "C" fn(TaskHandle) -> i32
        );
        unsafe { f(t) }
    }
    fn clear(&self, t: TaskHandle) -> i32 {
        let f = sym!(
            self,
            "DAQmxClearTask",
            unsafe extern "C" fn(TaskHandle) -> i32
        );
        unsafe { f(t) }
    }
    /// (status, samples per channel read)
    fn read_f64(
        &self,
        t: TaskHandle,
        n: i32,
        timeout: f64,
        fill: u32,
        out: &mut [f64],
    ) -> (i32, i32) {
        let f = sym!(
            self,
            "DAQmxReadAnalogF64",
            unsafe extern "C" fn(
                TaskHandle,
                i32,
                f64,
                u32,
                *mut f64,
                u32,
                *mut i32,
                *mut u32,
            ) -> i32
        );
        let mut read = -1;
        let s = unsafe {
            f(
                t,
                n,
                timeout,
                fill,
                out.as_mut_ptr(),
                out.len() as u32,
                &mut read,
                std::ptr::null_mut(),
            )
        };
        (s, read)
    }
    fn write_f64(&self, t: TaskHandle, n: i32, auto: bool, data: &[f64]) -> (i32, i32) {
        let f = sym!(
            self,
            "DAQmxWriteAnalogF64",
            unsafe extern "C" fn(
                TaskHandle,
                i32,
                u32,
                f64,
                u32,
                *const f64,
                *mut i32,
                *mut u32,
            ) -> i32
        );
        let mut w = -1;
        let s = unsafe {
            f(
                t,
                n,
                auto as u32,
                10.0,
                DAQMX_VAL_GROUP_BY_CHANNEL,
                data.as_ptr(),
                &mut w,
                std::ptr::null_mut(),
            )
        };
        (s, w)
    }
    fn write_scalar(&self, t: TaskHandle, v: f64) -> i32 {
        let f = sym!(
            self,
            "DAQmxWriteAnalogScalarF64",
            unsafe extern "C" fn(TaskHandle, u32, f64, f64, *mut u32) -> i32
        );
        unsafe { f(t, 1, 1.0, v, std::ptr::null_mut()) }
    }
    fn error_string(&self, code: i32) -> String {
        let f = sym!(
            self,
            "DAQmxGetErrorString",
            unsafe extern "C" fn(i32, *mut c_char, u32) -> i32
        );
        let n = unsafe { f(code, std::ptr::null_mut(), 0) };
        assert!(n > 0);
        let mut buf = vec![0u8; n as usize];
        assert_eq!(
            unsafe { f(code, buf.as_mut_ptr() as *mut c_char, n as u32) },
            0
        );
        String::from_utf8_lossy(&buf[..n as usize - 1]).into_owned()
    }
    fn extended(&self) -> String {
        let f = sym!(
            self,
            "DAQmxGetExtendedErrorInfo",
            unsafe extern "C" fn(*mut c_char, u32) -> i32
        );
        let mut buf = vec![0u8; 4096];
        assert_eq!(unsafe { f(buf.as_mut_ptr() as *mut c_char, 4096) }, 0);
        let end = buf.iter().position(|&c| c == 0).unwrap();
        String::from_utf8_lossy(&buf[..end]).into_owned()
    }
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len() as f64
}

#[test]
fn move_and_read_back_converge_with_the_lag() {
    let (_g, f) = fake();
    f.set("tau_ms", "20");
    f.set("sensor_noise_um", "0");
    let h = f.init_handle();
    assert!(h > 0);
    assert_eq!(f.write(30.0, 1, h), MCL_SUCCESS);
    let t0 = std::time::Instant::now();
    std::thread::sleep(std::time::Duration::from_millis(20));
    let p1 = f.read(1, h);
    let dt1 = t0.elapsed().as_secs_f64();
    // p(t) = 30 (1 − exp(−t/τ)), read within its 16-bit step (75 µm / 65535)
    let want1 = 30.0 * (1.0 - (-dt1 / 0.02).exp());
    let want_lo = 30.0 * (1.0 - (-0.020f64 / 0.02).exp());
    assert!(
        p1 >= want_lo - 0.002 && p1 <= want1 + 0.002,
        "p1 {p1}, between {want_lo} and {want1}"
    );
    std::thread::sleep(std::time::Duration::from_millis(200));
    let p2 = f.read(1, h);
    assert!((p2 - 30.0).abs() < 75.0 / 65535.0, "settled at {p2}");
    // the other axes did not move
    assert_eq!(f.read(2, h), 0.0);
    f.release(h);
}

#[test]
fn calibration_product_info_and_serial() {
    let (_g, f) = fake();
    let h = f.init_handle();
    assert_eq!(f.calibration(1, h), 75.0);
    assert_eq!(f.calibration(2, h), 75.0);
    assert_eq!(f.calibration(3, h), 50.0);
    assert_eq!(f.calibration(4, h), MCL_INVALID_AXIS as f64);
    let pinfo = sym!(
        f,
        "MCL_GetProductInfo",
        unsafe extern "C" fn(*mut ProductInformation, c_int) -> c_int
    );
    let mut p = ProductInformation::default();
    assert_eq!(std::mem::size_of::<ProductInformation>(), 11);
    assert_eq!(unsafe { pinfo(&mut p, h) }, MCL_SUCCESS);
    let (bitmap, id, adc) = (p.axis_bitmap, p.product_id, p.adc_resolution);
    assert_eq!((bitmap, id, adc), (0x07, 0x2003, 16));
    let serial = sym!(
        f,
        "MCL_GetSerialNumber",
        unsafe extern "C" fn(c_int) -> c_int
    );
    assert_eq!(unsafe { serial(h) }, 2847);
    f.release(h);
    f.set("serial", "3011");
    f.set("range_um", "100,100,20");
    let h = f.init_handle();
    assert_eq!(unsafe { serial(h) }, 3011);
    assert_eq!(f.calibration(3, h), 20.0);
}

#[test]
fn handle_lifecycle() {
    let (_g, f) = fake();
    assert_eq!(f.by_serial(2847), 0, "not grabbed yet");
    assert_eq!(f.grab_all(), 1);
    let h = f.by_serial(2847);
    assert!(h > 0);
    assert_eq!(f.by_serial(2848), 0);
    assert_eq!(f.init_handle(), 0, "the only Nano-Drive is held");
    let count = sym!(
        f,
        "MCL_NumberOfCurrentHandles",
        unsafe extern "C" fn() -> c_int
    );
    assert_eq!(unsafe { count() }, 1);
    let all = sym!(
        f,
        "MCL_GetAllHandles",
        unsafe extern "C" fn(*mut c_int, c_int) -> c_int
    );
    let mut hs = [0; 4];
    assert_eq!(unsafe { all(hs.as_mut_ptr(), 4) }, 1);
    assert_eq!(hs[0], h);
    f.release(h);
    assert_eq!(unsafe { count() }, 0);
    assert_eq!(f.write(1.0, 1, h), MCL_INVALID_HANDLE, "released handle");
    assert_eq!(f.read(1, h), MCL_INVALID_HANDLE as f64);
    assert_eq!(f.write(1.0, 1, 12345), MCL_INVALID_HANDLE, "never issued");
    let h2 = f.init_handle();
    assert!(h2 > 0 && h2 != h);
    assert_eq!(f.write(1.0, 0, h2), MCL_INVALID_AXIS);
    assert_eq!(f.write(1.0, 4, h2), MCL_INVALID_AXIS);
    assert_eq!(f.write(75.5, 1, h2), MCL_ARGUMENT_ERROR);
    assert_eq!(f.write(-0.1, 1, h2), MCL_ARGUMENT_ERROR);
    assert_eq!(f.write(f64::NAN, 1, h2), MCL_ARGUMENT_ERROR);
    assert_eq!(f.write(50.0, 3, h2), MCL_SUCCESS);
    assert_eq!(f.write(50.5, 3, h2), MCL_ARGUMENT_ERROR, "z range is 50 µm");
    let log = f.log();
    assert!(
        log.contains("MCL_ReleaseHandle(handle=") && log.contains("[released]"),
        "{log}"
    );
}

#[test]
fn stage_faults() {
    let (_g, f) = fake();
    f.faults("no_stage");
    assert_eq!(f.init_handle(), 0);
    assert_eq!(f.grab_all(), 0);
    f.faults("stage_unplug_after=2");
    let h = f.init_handle();
    assert!(h > 0);
    assert_eq!(f.write(1.0, 1, h), MCL_SUCCESS);
    assert!(f.read(1, h) >= 0.0);
    assert_eq!(f.write(2.0, 1, h), MCL_DEV_NOT_ATTACHED);
    assert_eq!(f.read(1, h), MCL_DEV_NOT_ATTACHED as f64);
    let attached = sym!(
        f,
        "MCL_DeviceAttached",
        unsafe extern "C" fn(c_int, c_int) -> c_uchar
    );
    assert_eq!(unsafe { attached(1, h) }, 0);
    f.release(h);
    f.faults("stage_stuck=x");
    let stuck_at = f.position(1);
    let h = f.init_handle();
    assert_eq!(f.write(20.0, 1, h), MCL_SUCCESS);
    assert_eq!(f.write(20.0, 2, h), MCL_SUCCESS);
    std::thread::sleep(std::time::Duration::from_millis(30));
    assert_eq!(f.position(1), stuck_at, "x stays where it stuck");
    assert!((f.position(2) - 20.0).abs() < 1e-3);
}

/// A finite read of n samples per channel on the board clock: the means are the scene's
/// signal at the stage position, and Sx changes sign across the bead (at the origin: the
/// middle of the range, 37.5 µm).
#[test]
fn finite_ai_sees_the_bead_at_the_stage_position() {
    let (_g, f) = fake();
    f.set("detector_noise_v", "0.001");
    f.set("tau_ms", "0.5");
    let h = f.init_handle();
    assert_eq!(f.write(25.0, 3, h), MCL_SUCCESS);
    assert_eq!(f.write(37.5, 2, h), MCL_SUCCESS);
    let mut sx = Vec::new();
    let mut sum = Vec::new();
    for x in [37.4, 37.5, 37.6] {
        assert_eq!(f.write(x, 1, h), MCL_SUCCESS);
        std::thread::sleep(std::time::Duration::from_millis(10));
        let t = f.create_task();
        assert_eq!(
            f.ai_chan(t, "Dev1/ai0:3", DAQMX_VAL_CFG_DEFAULT, -10.0, 10.0),
            0
        );
        assert_eq!(f.timing(t, "", 100e3, DAQMX_VAL_FINITE_SAMPS, 1000), 0);
        assert_eq!(f.start(t), 0);
        let mut buf = vec![0.0; 4000];
        let t0 = std::time::Instant::now();
        let (s, n) = f.read_f64(t, 1000, 5.0, DAQMX_VAL_GROUP_BY_CHANNEL, &mut buf);
        assert_eq!((s, n), (0, 1000));
        assert!(
            t0.elapsed().as_secs_f64() >= 0.0095,
            "1000 samples at 100 kS/s take 10 ms"
        );
        sx.push(mean(&buf[0..1000]));
        sum.push(mean(&buf[2000..3000]));
        // ai3: the x sensor monitor, 0–10 V over 75 µm
        let mon = mean(&buf[3000..4000]);
        assert!(
            (mon - x / 75.0 * 10.0).abs() < 2e-3,
            "monitor {mon} V at x = {x}"
        );
        assert_eq!(f.clear(t), 0);
    }
    // Sx is odd in x about the bead: opposite signs, equal magnitudes (noise 1 mV / √1000)
    assert!(sx[0] * sx[2] < 0.0, "Sx {sx:?}");
    assert!(
        (sx[0] + sx[2]).abs() < 0.1 * sx[0].abs() + 2e-4,
        "Sx {sx:?}"
    );
    assert!(
        sx[1].abs() < 0.1 * sx[0].abs() + 2e-4,
        "Sx at the bead {sx:?}"
    );
    // the sum is near 5 V
    assert!(sum.iter().all(|s| (s - 5.0).abs() < 0.5), "sum {sum:?}");
    // against the simulator directly (an independent call path: the renderer at the scene point)
    let r = bfpscope::instrument::sim::Renderer::checked(
        &bfpscope::optics::Optics::default(),
        &bfpscope::script::motion::reference_bead_scene(),
        bfpscope::optics::template::TemplateSpec::default(),
    )
    .unwrap();
    let g = r.render_grid_ideal(&[-0.1], &[0.0], 0.0);
    assert!(
        (sx[0] - g[0][0]).abs() < 0.02 * g[0][0].abs() + 2e-4,
        "Sx {} vs simulator {}",
        sx[0],
        g[0][0]
    );
}

#[test]
fn ai_on_the_ao_clock_follows_the_ramp_with_the_lag() {
    let (_g, f) = fake();
    f.set("tau_ms", "1");
    f.set("sensor_noise_um", "0");
    f.set("detector_noise_v", "0");
    let rate = 20e3;
    let n = 400usize;
    // AO: a ramp 0 → 4 V on ao0 (x external input: 0 → 30 µm), finite
    let ao = f.create_task();
    assert_eq!(f.ao_chan(ao, "Dev1/ao0"), 0);
    assert_eq!(f.timing(ao, "", rate, DAQMX_VAL_FINITE_SAMPS, n as u64), 0);
    let ramp: Vec<f64> = (0..n).map(|k| 4.0 * k as f64 / (n - 1) as f64).collect();
    assert_eq!(f.write_f64(ao, n as i32, false, &ramp), (0, n as i32));
    // AI: on the AO sample clock, started by the AO start trigger
    let ai = f.create_task();
    assert_eq!(f.ai_chan(ai, "Dev1/ai3", DAQMX_VAL_DIFF, -10.0, 10.0), 0);
    assert_eq!(
        f.timing(
            ai,
            "/Dev1/ao/SampleClock",
            rate,
            DAQMX_VAL_CONT_SAMPS,
            n as u64
        ),
        0
    );
    assert_eq!(f.start_trigger(ai, "/Dev1/ao/StartTrigger"), 0);
    assert_eq!(f.start(ai), 0);
    assert_eq!(f.start(ao), 0);
    let mut got = Vec::new();
    let mut buf = vec![0.0; 100];
    while got.len() < n {
        let (s, k) = f.read_f64(ai, 100, 2.0, DAQMX_VAL_GROUP_BY_SCAN_NUMBER, &mut buf);
        assert_eq!((s, k), (0, 100));
        got.extend_from_slice(&buf);
    }
    // the clock stopped with the finite generation: no more samples
    let (s, _) = f.read_f64(ai, 1, 0.05, DAQMX_VAL_GROUP_BY_SCAN_NUMBER, &mut buf);
    assert_eq!(s, -200284);
    // expected: sample k sees the first-order response to the held AO steps before edge k
    let dt = 1.0 / rate;
    let a = (-dt / 1e-3f64).exp();
    let mut p = 0.0; // the stage starts at 0
    for (k, &v) in got.iter().enumerate() {
        let want_v = p / 75.0 * 10.0;
        assert!(
            (v - want_v).abs() < 2.0 * 20.0 / 65536.0 + 1e-9,
            "sample {k}: {v} V, want {want_v}"
        );
        let target = ramp[k] / 10.0 * 75.0;
        p = target + (p - target) * a;
    }
    // the lag: at the end the sensor trails the ramp by about slope·τ
    let slope = 4.0 / ((n - 1) as f64 * dt); // V/s
    let trail = ramp[n - 1] - got[n - 1];
    assert!(
        (trail - slope * 1e-3).abs() < 0.1 * slope * 1e-3 + 0.01,
        "trail {trail} V, slope·τ {}",
        slope * 1e-3
    );
    // AO holds its last value after the generation; clearing keeps it
    assert_eq!(f.clear(ai), 0);
    assert_eq!(f.clear(ao), 0);
    assert!((f.ao_voltage(0) - 4.0).abs() < 1e-12);
    assert!((f.position(1) - 30.0).abs() < 0.01);
}

#[test]
fn ao_dc_hold_moves_the_stage_and_the_log_shows_it() {
    let (_g, f) = fake();
    f.set("tau_ms", "0");
    let ao = f.create_task();
    assert_eq!(f.ao_chan(ao, "Dev1/ao1"), 0);
    assert_eq!(f.write_scalar(ao, 5.0), 0);
    assert!((f.position(2) - 37.5).abs() < 1e-12);
    assert_eq!(f.stop(ao), 0);
    assert_eq!(f.clear(ao), 0);
    assert_eq!(f.ao_voltage(1), 5.0);
    let log = f.log();
    assert!(
        log.contains(
            "DAQmxWriteAnalogScalarF64(_unnamedTask<0>, autoStart=1, timeout=1, value=5) -> 0"
        ),
        "{log}"
    );
    assert!(
        log.contains("DAQmxClearTask(_unnamedTask<0>) -> 0"),
        "{log}"
    );
    // a device reset drives both AO terminals to 0 V: the stage follows
    let reset = sym!(
        f,
        "DAQmxResetDevice",
        unsafe extern "C" fn(*const c_char) -> i32
    );
    let dev = CString::new("Dev1").unwrap();
    assert_eq!(unsafe { reset(dev.as_ptr()) }, 0);
    assert_eq!(f.ao_voltage(1), 0.0);
    assert_eq!(f.position(2), 0.0);
}

#[test]
fn argument_errors_have_nis_codes_and_texts() {
    let (_g, f) = fake();
    let t = f.create_task();
    assert_eq!(
        f.ai_chan(t, "Dev9/ai0", DAQMX_VAL_DIFF, -10.0, 10.0),
        -200220
    );
    assert!(
        f.extended().contains("Device identifier is invalid."),
        "{}",
        f.extended()
    );
    assert_eq!(
        f.ai_chan(t, "Dev1/ai4", DAQMX_VAL_DIFF, -10.0, 10.0),
        -200170
    );
    assert!(f
        .extended()
        .starts_with("Physical channel specified does not exist on this device."));
    assert_eq!(
        f.ai_chan(t, "Dev1/ao0", DAQMX_VAL_DIFF, -10.0, 10.0),
        -200430
    );
    assert_eq!(
        f.ai_chan(t, "Dev1/ai0", DAQMX_VAL_RSE, -10.0, 10.0),
        -200077
    );
    assert!(
        f.extended().contains("DAQmx_AI_TermCfg"),
        "{}",
        f.extended()
    );
    assert_eq!(
        f.ai_chan(t, "Dev1/ai0", DAQMX_VAL_DIFF, -50.0, 50.0),
        -200077,
        "no ±50 V range"
    );
    assert!(f.extended().contains("DAQmx_AI_"), "{}", f.extended());
    assert_eq!(f.ai_chan(t, "Dev1/ai0", DAQMX_VAL_DIFF, 1.0, -1.0), -200082);
    assert_eq!(f.ai_chan(t, "Dev1/ai0:1", DAQMX_VAL_DIFF, -1.0, 1.0), 0);
    assert_eq!(
        f.timing(t, "", 1e6, DAQMX_VAL_FINITE_SAMPS, 100),
        -200077,
        "above 800 kS/s"
    );
    let ext = f.extended();
    assert!(
        ext.contains("DAQmx_SampClk_Rate")
            && ext.contains("Requested Value: 1e6")
            && ext.contains("Status Code: -200077"),
        "{ext}"
    );
    assert_eq!(
        f.timing(t, "", 800e3, DAQMX_VAL_FINITE_SAMPS, 1),
        -200077,
        "finite needs ≥ 2 samples"
    );
    assert_eq!(
        f.timing(t, "/Dev1/PFI42", 1e3, DAQMX_VAL_FINITE_SAMPS, 10),
        -89120
    );
    assert_eq!(f.timing(t, "", 800e3, DAQMX_VAL_FINITE_SAMPS, 10), 0);
    // a read on a cleared task
    assert_eq!(f.clear(t), 0);
    let mut buf = vec![0.0; 20];
    assert_eq!(f.read_f64(t, 10, 1.0, 0, &mut buf).0, -200088);
    assert_eq!(f.clear(t), -200088);
    assert_eq!(
        f.error_string(-200088),
        "Task specified is invalid or does not exist."
    );
    assert!(f
        .error_string(-200284)
        .starts_with("Some or all of the samples requested have not yet been acquired."));
    assert!(f
        .error_string(-200279)
        .starts_with("The application is not able to keep up with the hardware acquisition."));
    // a timeout: 1000 samples at 1 kS/s (1 s) with a 50 ms timeout
    let t = f.create_task();
    assert_eq!(f.ai_chan(t, "Dev1/ai0", DAQMX_VAL_DIFF, -10.0, 10.0), 0);
    assert_eq!(f.timing(t, "", 1e3, DAQMX_VAL_FINITE_SAMPS, 1000), 0);
    assert_eq!(f.start(t), 0);
    let mut buf = vec![0.0; 1000];
    let t0 = std::time::Instant::now();
    let (s, n) = f.read_f64(t, 1000, 0.05, 0, &mut buf);
    let el = t0.elapsed().as_secs_f64();
    assert_eq!(s, -200284);
    assert!(
        (40..=60).contains(&n),
        "read {n} samples in {el} s before the timeout"
    );
    assert!((0.045..0.2).contains(&el), "{el}");
    // a read beyond the finite end
    assert_eq!(f.read_f64(t, 1000, 0.01, 0, &mut buf).0, -200278);
    assert_eq!(f.clear(t), 0);
    // AO: values outside the channel's range
    let ao = f.create_task();
    assert_eq!(f.ao_chan(ao, "Dev1/ao0"), 0);
    assert_eq!(f.write_scalar(ao, 10.5), -200561);
    assert_eq!(f.ao_voltage(0), 0.0);
    assert_eq!(f.clear(ao), 0);
}

#[test]
fn continuous_stream_overflows_when_not_read() {
    let (_g, f) = fake();
    let t = f.create_task();
    assert_eq!(f.ai_chan(t, "Dev1/ai0", DAQMX_VAL_DIFF, -10.0, 10.0), 0);
    assert_eq!(f.timing(t, "", 100e3, DAQMX_VAL_CONT_SAMPS, 1000), 0);
    let cfg = sym!(
        f,
        "DAQmxCfgInputBuffer",
        unsafe extern "C" fn(TaskHandle, u32) -> i32
    );
    // a buffer of 20000 samples (200 ms at 100 kS/s): reads in time tolerate a loaded machine's
    // scheduling delays of well over 100 ms (a 2000-sample buffer overflowed under load)
    assert_eq!(unsafe { cfg(t, 20000) }, 0);
    assert_eq!(f.start(t), 0);
    let mut buf = vec![0.0; 500];
    // read in time: fine
    for _ in 0..4 {
        assert_eq!(
            f.read_f64(t, 500, 1.0, 0, &mut buf),
            (0, 500),
            "{}",
            f.log()
        );
    }
    // 20000 samples are 200 ms at 100 kS/s: wait 400 ms
    std::thread::sleep(std::time::Duration::from_millis(400));
    assert_eq!(f.read_f64(t, 500, 1.0, 0, &mut buf).0, -200279);
    assert!(f.extended().contains("Status Code: -200279"));
    assert_eq!(
        f.read_f64(t, 500, 1.0, 0, &mut buf).0,
        -200279,
        "stays overwritten"
    );
    // a restart reads again
    assert_eq!(f.stop(t), 0);
    assert_eq!(f.start(t), 0);
    assert_eq!(f.read_f64(t, 500, 1.0, 0, &mut buf), (0, 500));
    assert_eq!(f.clear(t), 0);
}

#[test]
fn daq_faults() {
    let (_g, f) = fake();
    f.faults("daq_missing");
    let t = f.create_task();
    assert_eq!(
        f.ai_chan(t, "Dev1/ai0", DAQMX_VAL_DIFF, -10.0, 10.0),
        -200220
    );
    assert_eq!(f.clear(t), 0);
    f.faults("daq_removed_after_reads=2");
    let t = f.create_task();
    assert_eq!(f.ai_chan(t, "Dev1/ai0", DAQMX_VAL_DIFF, -10.0, 10.0), 0);
    assert_eq!(f.timing(t, "", 100e3, DAQMX_VAL_CONT_SAMPS, 1000), 0);
    assert_eq!(f.start(t), 0);
    let mut buf = vec![0.0; 100];
    assert_eq!(f.read_f64(t, 100, 1.0, 0, &mut buf).0, 0);
    assert_eq!(f.read_f64(t, 100, 1.0, 0, &mut buf).0, 0);
    assert_eq!(f.read_f64(t, 100, 1.0, 0, &mut buf).0, -201003);
    assert!(f.extended().starts_with("Device cannot be accessed."));
    assert_eq!(f.clear(t), 0);
    f.faults("read_timeout");
    let t = f.create_task();
    assert_eq!(f.ai_chan(t, "Dev1/ai0", DAQMX_VAL_DIFF, -10.0, 10.0), 0);
    assert_eq!(f.timing(t, "", 100e3, DAQMX_VAL_FINITE_SAMPS, 100), 0);
    assert_eq!(f.read_f64(t, 100, 0.02, 0, &mut buf), (-200284, 0));
    assert_eq!(f.clear(t), 0);
    f.faults("overflow_after_reads=1");
    let t = f.create_task();
    assert_eq!(f.ai_chan(t, "Dev1/ai0", DAQMX_VAL_DIFF, -10.0, 10.0), 0);
    assert_eq!(f.timing(t, "", 100e3, DAQMX_VAL_CONT_SAMPS, 1000), 0);
    assert_eq!(f.start(t), 0);
    assert_eq!(f.read_f64(t, 100, 1.0, 0, &mut buf).0, 0);
    assert_eq!(f.read_f64(t, 100, 1.0, 0, &mut buf).0, -200279);
    assert_eq!(f.clear(t), 0);
}

/// A continuous AO stream with regeneration off (NI-DAQmx's behaviour): its buffer holds what
/// was written before the start; `DAQmxGetWriteSpaceAvail` tells the room freed by the samples
/// played; a write that brings more than the room waits until the generation has played
/// enough (here 100 of 1000 samples at 10 kS/s: ≈ 10 ms; 800: ≈ 80 ms), and one that cannot
/// get its room before its timeout fails with −200292 having written nothing.
#[test]
fn a_stream_write_into_a_full_buffer_waits_for_room_and_the_space_is_told() {
    let (_g, f) = fake();
    let rate = 10e3;
    let ao = f.create_task();
    assert_eq!(f.ao_chan(ao, "Dev1/ao0"), 0);
    assert_eq!(f.timing(ao, "", rate, DAQMX_VAL_CONT_SAMPS, 1000), 0);
    let regen = sym!(
        f,
        "DAQmxSetWriteRegenMode",
        unsafe extern "C" fn(TaskHandle, i32) -> i32
    );
    assert_eq!(unsafe { regen(ao, 10158) }, 0); // DAQmx_Val_DoNotAllowRegen
    let space = sym!(
        f,
        "DAQmxGetWriteSpaceAvail",
        unsafe extern "C" fn(TaskHandle, *mut u32) -> i32
    );
    let free = || {
        let mut v = u32::MAX;
        assert_eq!(unsafe { space(ao, &mut v) }, 0);
        v
    };
    let block = vec![1.0; 1000];
    assert_eq!(f.write_f64(ao, 1000, false, &block), (0, 1000));
    assert_eq!(free(), 0, "the first write sizes the buffer and fills it");
    assert_eq!(f.start(ao), 0);
    let t = std::time::Instant::now();
    assert_eq!(f.write_f64(ao, 100, false, &block[..100]), (0, 100));
    let waited = t.elapsed().as_secs_f64();
    assert!(
        (0.008..0.05).contains(&waited),
        "waited {waited} s for 100 samples"
    );
    std::thread::sleep(std::time::Duration::from_millis(30));
    // ≈ 30 ms more played: ≈ 300 samples of room (the clock runs on meanwhile)
    let room = free();
    assert!((250..=450).contains(&room), "room {room}");
    // a write of the room never waits
    let t = std::time::Instant::now();
    let n = room as usize;
    assert_eq!(f.write_f64(ao, n as i32, false, &block[..n]), (0, n as i32));
    assert!(t.elapsed().as_secs_f64() < 0.005, "{:?}", t.elapsed());
    // 800 samples with a 10 ms timeout: not enough room in time
    let w = sym!(
        f,
        "DAQmxWriteAnalogF64",
        unsafe extern "C" fn(TaskHandle, i32, u32, f64, u32, *const f64, *mut i32, *mut u32) -> i32
    );
    let mut wrote = -1;
    let t = std::time::Instant::now();
    let s = unsafe {
        w(
            ao,
            800,
            0,
            0.01,
            DAQMX_VAL_GROUP_BY_CHANNEL,
            block.as_ptr(),
            &mut wrote,
            std::ptr::null_mut(),
        )
    };
    assert_eq!((s, wrote), (-200292, 0));
    let waited = t.elapsed().as_secs_f64();
    assert!((0.009..0.05).contains(&waited), "waited {waited} s");
    assert!(
        f.extended()
            .contains("could not be written to the buffer yet"),
        "{}",
        f.extended()
    );
    assert_eq!(f.clear(ao), 0);
}
