//! The wgpu device the GPU passes run on: [`GpuContext`] owns the instance, the adapter, the
//! device and its queue, and remembers the adapter's description and the limits the device
//! was created with (the slot buffer's size comes from them).
//!
//! Any adapter will do, a software one included (Mesa's lavapipe gives a Vulkan adapter named
//! `llvmpipe` on machines without a GPU). The usual wgpu environment variables choose:
//! `WGPU_BACKEND` (e.g. `vulkan`, `gl`) the backends, `WGPU_ADAPTER_NAME` a substring of the
//! adapter's name, `WGPU_POWER_PREF` the power preference. No adapter is an error
//! ([`GpuError`]), never a silent fallback to the CPU.
//!
//! The device's errors are caught, not left to wgpu's default handler (which panics): an error
//! no one scoped (a validation, out-of-memory or internal error) and the loss of the device are
//! recorded in the context, logged, and from then on every backend call
//! returns them as a [`BackendError`]. The window viewer and a headless run then end with the
//! reason instead of a panic.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use arbor_client_core::backend::BackendError;

/// Why no GPU device could be had.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    #[error(
        "no GPU adapter for backends {backends:?}: {source} (install a Vulkan driver — Mesa's \
         lavapipe works without a GPU — or choose backends with WGPU_BACKEND)"
    )]
    NoAdapter {
        backends: wgpu::Backends,
        source: wgpu::RequestAdapterError,
    },
    #[error("WGPU_ADAPTER_NAME={name:?} matches none of the adapters: {found}")]
    NoAdapterNamed { name: String, found: String },
    #[error("requesting a device from {adapter}: {source}")]
    Device {
        adapter: String,
        source: wgpu::RequestDeviceError,
    },
}

/// A wgpu device and what it was made from.
#[derive(Debug)]
pub struct GpuContext {
    pub instance: wgpu::Instance,
    pub adapter: wgpu::Adapter,
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    /// The adapter's name, backend and device type.
    pub info: wgpu::AdapterInfo,
    /// The limits the device was created with (the adapter's own).
    pub limits: wgpu::Limits,
    /// The first fault the device reported, if any.
    fault: Arc<DeviceFault>,
}

/// The first error a device reported outside an error scope, or its loss. A loss replaces an
/// earlier error: the commands a lost device refuses are reported as validation errors before
/// the loss itself is, and the loss is the reason worth telling.
#[derive(Debug, Default)]
struct DeviceFault {
    /// Set once a fault is recorded (the check every backend call makes).
    faulted: AtomicBool,
    first: Mutex<Option<BackendError>>,
}

impl DeviceFault {
    /// Records `error` unless one is recorded already (a loss replaces an error that is not
    /// one).
    fn record(&self, error: BackendError) {
        let mut first = self.first.lock().unwrap_or_else(|e| e.into_inner());
        let replace = match (&*first, &error) {
            (None, _) => true,
            (Some(BackendError::DeviceLost(_)), _) => false,
            (Some(_), BackendError::DeviceLost(_)) => true,
            (Some(_), _) => false,
        };
        if replace {
            tracing::error!("GPU device fault: {error}");
            *first = Some(error);
            self.faulted.store(true, Ordering::Release);
        }
    }

    /// The recorded fault, if any.
    fn get(&self) -> Option<BackendError> {
        if !self.faulted.load(Ordering::Acquire) {
            return None;
        }
        self.first.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }
}

/// The [`BackendError`] for an error wgpu reports.
fn backend_error(e: &wgpu::Error) -> BackendError {
    match e {
        wgpu::Error::OutOfMemory { .. } => BackendError::OutOfMemory(e.to_string()),
        _ => BackendError::Device(e.to_string()),
    }
}

impl GpuContext {
    /// Opens a device on the adapter chosen by the environment (see the module docs), able to
    /// present to `compatible_surface` when given. Requests the adapter's full limits (the
    /// slot buffer wants the largest storage binding it has) and timestamp queries when
    /// supported (for the benchmark).
    pub fn new(compatible_surface: Option<&wgpu::Surface<'_>>) -> Result<GpuContext, GpuError> {
        let desc = wgpu::InstanceDescriptor::new_without_display_handle_from_env();
        let backends = desc.backends;
        let instance = wgpu::Instance::new(desc);
        Self::with_instance(instance, backends, compatible_surface)
    }

    /// [`GpuContext::new`] on an existing instance (a window viewer creates the instance with
    /// its display handle before the surface).
    pub fn with_instance(
        instance: wgpu::Instance,
        backends: wgpu::Backends,
        compatible_surface: Option<&wgpu::Surface<'_>>,
    ) -> Result<GpuContext, GpuError> {
        let adapter = pollster::block_on(pick_adapter(&instance, backends, compatible_surface))?;
        let info = adapter.get_info();
        let limits = adapter.limits();
        let required_features = adapter.features() & wgpu::Features::TIMESTAMP_QUERY;
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("arbor"),
            required_features,
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|source| GpuError::Device {
            adapter: describe(&info),
            source,
        })?;
        let fault = Arc::new(DeviceFault::default());
        let on_error = fault.clone();
        device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
            on_error.record(backend_error(&e));
        }));
        let on_loss = fault.clone();
        device.set_device_lost_callback(move |reason, message| {
            let reason = match reason {
                wgpu::DeviceLostReason::Destroyed => "destroyed",
                wgpu::DeviceLostReason::Unknown => "lost by the driver",
            };
            on_loss.record(BackendError::DeviceLost(if message.is_empty() {
                reason.to_owned()
            } else {
                format!("{reason}: {message}")
            }));
        });
        Ok(GpuContext {
            instance,
            adapter,
            device,
            queue,
            info,
            limits,
            fault,
        })
    }

    /// The device's first fault (see the module docs) as an error, or `Ok`.
    pub fn check(&self) -> Result<(), BackendError> {
        self.fault.get().map_or(Ok(()), Err)
    }

    /// Records a fault found by the caller (a failed read-back), unless one is recorded; returns
    /// the fault in effect.
    pub fn fail(&self, error: BackendError) -> BackendError {
        self.fault.record(error.clone());
        self.fault.get().unwrap_or(error)
    }

    /// `name (backend, device type)`, for logs and reports.
    pub fn describe(&self) -> String {
        describe(&self.info)
    }

    /// Whether the adapter is a software one (lavapipe): its passes run on the CPU's cores.
    pub fn is_software(&self) -> bool {
        self.info.device_type == wgpu::DeviceType::Cpu
    }
}

fn describe(info: &wgpu::AdapterInfo) -> String {
    format!("{} ({:?}, {:?})", info.name, info.backend, info.device_type)
}

async fn pick_adapter(
    instance: &wgpu::Instance,
    backends: wgpu::Backends,
    surface: Option<&wgpu::Surface<'_>>,
) -> Result<wgpu::Adapter, GpuError> {
    if let Ok(name) = std::env::var("WGPU_ADAPTER_NAME") {
        let wanted = name.to_lowercase();
        let adapters = instance.enumerate_adapters(backends).await;
        let mut found = Vec::new();
        for adapter in adapters {
            let info = adapter.get_info();
            if surface.is_some_and(|s| !adapter.is_surface_supported(s)) {
                continue;
            }
            if info.name.to_lowercase().contains(&wanted) {
                return Ok(adapter);
            }
            found.push(describe(&info));
        }
        return Err(GpuError::NoAdapterNamed {
            name,
            found: if found.is_empty() {
                "none".into()
            } else {
                found.join(", ")
            },
        });
    }
    instance
        .request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::from_env()
                .unwrap_or(wgpu::PowerPreference::HighPerformance),
            compatible_surface: surface,
            ..Default::default()
        })
        .await
        .map_err(|source| GpuError::NoAdapter { backends, source })
}
