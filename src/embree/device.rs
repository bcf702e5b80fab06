//! The Embree device handle ([`Device`]) and the crate's Embree error type.
use std::ffi::CStr;
use std::os::raw::{c_char, c_void};
use std::ptr::NonNull;
use std::sync::{Arc, Mutex};

use super::sys;

/// Errors reported by Embree or by the checks made before handing data to it.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum EmbreeError {
    #[error("Embree: cannot create a device ({code}){}", fmt_msg(.message))]
    NewDevice { code: String, message: String },
    #[error("Embree error {code} during {during}{}", fmt_msg(.message))]
    Call {
        during: &'static str,
        code: String,
        message: String,
    },
    #[error("invalid mesh for Embree: {0}")]
    InvalidMesh(String),
}

fn fmt_msg(m: &str) -> String {
    if m.is_empty() {
        String::new()
    } else {
        format!(": {m}")
    }
}

fn code_name(code: sys::RTCError::Type) -> String {
    use sys::RTCError::*;
    match code {
        RTC_ERROR_NONE => "NONE",
        RTC_ERROR_UNKNOWN => "UNKNOWN",
        RTC_ERROR_INVALID_ARGUMENT => "INVALID_ARGUMENT",
        RTC_ERROR_INVALID_OPERATION => "INVALID_OPERATION",
        RTC_ERROR_OUT_OF_MEMORY => "OUT_OF_MEMORY",
        RTC_ERROR_UNSUPPORTED_CPU => "UNSUPPORTED_CPU",
        RTC_ERROR_CANCELLED => "CANCELLED",
        _ => return format!("code {code}"),
    }
    .to_string()
}

/// The device and the last message its error callback received. Shared (`Arc`) by every
/// scene made from it, so the device outlives its scenes whatever order they are dropped in.
pub(crate) struct DeviceInner {
    raw: NonNull<sys::RTCDeviceTy>,
    /// Written by the error callback, read by [`DeviceInner::check`]. Boxed so its address,
    /// handed to Embree as `userPtr`, is stable.
    last_message: Box<Mutex<String>>,
}

// SAFETY: an `RTCDevice` is a thread-safe, reference-counted object in Embree (all API
// calls on it may be made from any thread); the only Rust-side state is behind a Mutex.
unsafe impl Send for DeviceInner {}
// SAFETY: as above; `&DeviceInner` only exposes `rtcGetDeviceError` (thread-local error
// state inside Embree) and the Mutex.
unsafe impl Sync for DeviceInner {}

impl Drop for DeviceInner {
    fn drop(&mut self) {
        // SAFETY: `raw` came from `rtcNewDevice` and this is its only owner; every scene
        // holding an `Arc<DeviceInner>` has been dropped (and released) before this runs.
        unsafe { sys::rtcReleaseDevice(self.raw.as_ptr()) };
    }
}

/// Embree's error callback: stores the message for the next [`DeviceInner::check`].
/// Never unwinds into C: locking failures are ignored.
unsafe extern "C" fn error_callback(
    user: *mut c_void,
    _code: sys::RTCError::Type,
    msg: *const c_char,
) {
    if user.is_null() || msg.is_null() {
        return;
    }
    // SAFETY: `user` is the `Mutex<String>` boxed in the `DeviceInner` that registered this
    // callback; the box lives until the device is released, after which Embree calls no
    // callback. `msg` is a NUL-terminated string valid for the duration of the call.
    let (slot, text) = unsafe { (&*(user as *const Mutex<String>), CStr::from_ptr(msg)) };
    if let Ok(mut s) = slot.lock() {
        *s = text.to_string_lossy().into_owned();
    }
}

impl DeviceInner {
    pub(crate) fn raw(&self) -> sys::RTCDevice {
        self.raw.as_ptr()
    }

    /// Turns the device's pending error (if any) into an `Err`.
    pub(crate) fn check(&self, during: &'static str) -> Result<(), EmbreeError> {
        // SAFETY: `raw` is a live device handle.
        let code = unsafe { sys::rtcGetDeviceError(self.raw.as_ptr()) };
        if code == sys::RTCError::RTC_ERROR_NONE {
            return Ok(());
        }
        let message = self
            .last_message
            .lock()
            .map(|mut s| std::mem::take(&mut *s))
            .unwrap_or_default();
        Err(EmbreeError::Call {
            during,
            code: code_name(code),
            message,
        })
    }
}

/// An Embree device (RAII). Cheap to clone: clones share one `RTCDevice`.
#[derive(Clone)]
pub struct Device {
    pub(crate) inner: Arc<DeviceInner>,
}

impl std::fmt::Debug for Device {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Device").finish_non_exhaustive()
    }
}

impl Device {
    /// Creates a device with Embree's default configuration and an error callback.
    pub fn new() -> Result<Device, EmbreeError> {
        // SAFETY: a null config string selects the defaults.
        let raw = unsafe { sys::rtcNewDevice(std::ptr::null()) };
        let Some(raw) = NonNull::new(raw) else {
            // SAFETY: with a null device, rtcGetDeviceError reports the thread's last
            // device-creation error.
            let code = unsafe { sys::rtcGetDeviceError(std::ptr::null_mut()) };
            return Err(EmbreeError::NewDevice {
                code: code_name(code),
                message: String::new(),
            });
        };
        let inner = DeviceInner {
            raw,
            last_message: Box::new(Mutex::new(String::new())),
        };
        let user = &*inner.last_message as *const Mutex<String> as *mut c_void;
        // SAFETY: `raw` is live; `user` points into the box owned by `inner`, which outlives
        // the device (it is released in `inner`'s Drop before the box is freed); the
        // callback only reads through it as `&Mutex<String>`.
        unsafe { sys::rtcSetDeviceErrorFunction(raw.as_ptr(), Some(error_callback), user) };
        inner.check("rtcNewDevice")?;
        Ok(Device {
            inner: Arc::new(inner),
        })
    }
}
