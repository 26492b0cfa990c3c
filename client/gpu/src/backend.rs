//! [`GpuBackend`]: the analysis pass, the slot upload and the render pass on a wgpu device
//! ([`Backend`] implementation).
//!
//! It owns the GPU copy of the incore buffer — one storage buffer of node records and one per
//! held attribute channel, each the CPU [`SlotBuffer`] array byte for byte (padded to 4 bytes),
//! so "GPU buffer == CPU buffer" is a byte comparison ([`GpuBackend::read_back_nodes`],
//! [`GpuBackend::read_back_attributes`]) — the two compute pipelines, the feedback buffers and
//! the render target.
//!
//! - **Sizing.** [`GpuBackend::max_slots`] is what one storage binding can cover
//!   (`max_storage_buffer_binding_size`, 128 MiB on lavapipe) divided by the largest per-slot
//!   array (the nodes, `8·N` bytes). The buffers are allocated on the first upload from
//!   `slots.capacity()`, and reallocated if the slot buffer's shape changes; the first upload
//!   after an allocation copies everything.
//! - **Upload.** One `queue.write_buffer` per planned slot range per array; calls and bytes
//!   are counted in [`UploadStats`].
//! - **Analysis waits while that is cheap, else it is pipelined** ([`FeedbackMode`]).
//!   - Pipelined: [`Backend::analyse`] submits this cycle's pass, copies its result into one
//!     of two staging buffers and requests the mapping, and returns the newest read-back that
//!     has completed by then — normally the *previous* cycle's — without ever waiting (only a
//!     non-blocking `device.poll`). So feedback lags one cycle; when nothing new has completed,
//!     `out` keeps the last feedback (the core then re-marks the same visible slots rather
//!     than seeing an empty frame), and when both staging buffers are still in flight this
//!     cycle's pass is skipped.
//!   - Waiting: the pass's own result, like the CPU twin's. A late feedback costs a cycle per
//!     round of refinement, and describes the previous camera while it moves, so a moving
//!     view never knew itself (no bias control, no eviction outside it). On an H100 the wait
//!     is about a millisecond, and lion-1k at 256², 12 MiB, converged in 47–68 cycles
//!     pipelined against 23 on the CPU backend.
//!   - [`FeedbackMode::Auto`] (the default) waits for the passes of frames up to
//!     [`WAIT_FRAME_PIXELS_MAX`] while the waits stay within [`WAIT_BELOW`]; after a longer
//!     one it pipelines for [`PIPELINE_CYCLES`] and then tries again. Going from pipelining to
//!     waiting first hands back what is in flight. Larger frames pipeline. A software adapter
//!     (lavapipe) runs the pass on the client's own cores, where pipelining overlaps nothing:
//!     there it always waits (lion-1k 256², 12 MiB: 20 cycles, 0.66 s, against 28–51 cycles
//!     with the 4 ms rule and 43 pipelined). [`GpuBackend::analyse_blocking`] always waits (tests,
//!     benchmarks).
//! - **Render** writes an `rgba8unorm` storage texture ([`GpuBackend::target_view`]);
//!   [`Backend::render`] also reads it back (rows padded to 256 bytes for the copy).
//!
//! Pipeline labels and entry points are the CPU module names, `"analysis"` and `"render"`.

use std::sync::Arc;
use std::sync::atomic::{AtomicU8, Ordering};
use std::time::{Duration, Instant};

use arbor_proto::{Channel, Node};

use super::context::GpuContext;
use super::layout::{FeedbackSample, FrameUniform};
use super::shaders;
use arbor_client_core::analysis::{AnalysisConfig, Feedback, grid_pixels};
use arbor_client_core::backend::{Backend, BackendError, PassInput};
use arbor_client_core::camera::Camera;
use arbor_client_core::image::Image;
use arbor_client_core::incore::{IncoreView, SceneFrame};
use arbor_client_core::render::Light;
use arbor_client_core::slots::SlotBuffer;
use arbor_client_core::traverse::Lod;
use arbor_client_core::upload::UploadPlan;

/// How [`Backend::analyse`] hands its feedback back (see the module docs).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum FeedbackMode {
    /// Wait for the passes of frames up to [`WAIT_FRAME_PIXELS_MAX`] while the waits stay within
    /// [`WAIT_BELOW`]; after a longer one, pipeline for [`PIPELINE_CYCLES`].
    #[default]
    Auto,
    /// Always wait for this cycle's pass.
    Wait,
    /// Never wait: the newest completed read-back, normally the previous cycle's.
    Pipelined,
}

impl FeedbackMode {
    /// Parses `auto`, `wait` or `pipelined` (the CLI spelling).
    pub fn parse(text: &str) -> Option<Self> {
        match text {
            "auto" => Some(Self::Auto),
            "wait" => Some(Self::Wait),
            "pipelined" => Some(Self::Pipelined),
            _ => None,
        }
    }
}

/// The longest wait for an analysis pass [`FeedbackMode::Auto`] accepts: a quarter of a
/// 60 Hz frame. The wait includes the GPU work queued before the pass (the cycle's uploads,
/// the last render). Measured on an H100 (lion-1k): 1–2 ms at 256², where waiting halves the
/// cycles to converge; 6–10 ms at 1024².
pub const WAIT_BELOW: Duration = Duration::from_millis(4);

/// The largest frame, in pixels, whose passes [`FeedbackMode::Auto`] waits for (256²). At 1024²
/// on an H100 (lion-1k, 64 MiB) waiting made the view wholly known from its second cycle, and
/// the presort over a million known samples then cost 25–35 ms a cycle: RMSE 0 at 0.79–0.91 s
/// against 0.51–0.57 s pipelined, where the knowledge grows over a dozen cycles while the load
/// limit sets the pace anyway.
pub const WAIT_FRAME_PIXELS_MAX: u64 = 1 << 16;

/// Cycles [`FeedbackMode::Auto`] pipelines after a wait over [`WAIT_BELOW`] before it waits
/// again to see whether the wait got shorter (the tail of a refinement samples few pixels).
pub const PIPELINE_CYCLES: u32 = 16;

/// Counters of the slot uploads.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct UploadStats {
    /// `write_buffer` calls in all.
    pub calls: u64,
    /// Bytes written in all.
    pub bytes: u64,
    /// Calls of the last [`Backend::upload`].
    pub last_calls: u64,
    /// Bytes of the last [`Backend::upload`].
    pub last_bytes: u64,
    /// Uploads of the whole buffer after an allocation.
    pub full_uploads: u64,
}

/// The GPU copy of the slot buffer.
#[derive(Debug)]
struct Store {
    capacity: u32,
    treelet_nodes: u32,
    nodes: wgpu::Buffer,
    /// Per channel in `Channel::ALL` order, the buffer when held.
    attributes: [Option<wgpu::Buffer>; 3],
    /// Bound in place of channels not held.
    dummy: wgpu::Buffer,
    channels: Vec<Channel>,
}

const MAP_IDLE: u8 = 0;
const MAP_PENDING: u8 = 1;
const MAP_READY: u8 = 2;
const MAP_FAILED: u8 = 3;

/// One staging buffer of the pipelined feedback read-back: the samples, then (with timestamp
/// queries) the pass's two ticks.
#[derive(Debug)]
struct Staging {
    buffer: wgpu::Buffer,
    state: Arc<AtomicU8>,
    /// Submission order, to pick the newest completed read-back.
    serial: u64,
    /// The cycle and pixels of the pass in flight here.
    cycle: u64,
    pixels: Vec<u32>,
}

/// The analysis pass's buffers, sized for up to `capacity` samples.
#[derive(Debug)]
struct FeedbackBuffers {
    capacity: u32,
    pixels: wgpu::Buffer,
    storage: wgpu::Buffer,
    staging: [Staging; 2],
    blocking: wgpu::Buffer,
}

/// Invocations per analysis workgroup (`@workgroup_size(64, 1, 1)` in `analysis.wgsl`).
const ANALYSIS_GROUP: u32 = 64;
/// Most workgroups one dispatch dimension may have.
const MAX_GROUPS: u32 = 65_535;

/// Workgroups `(x, y)` and invocations per row for an analysis pass over `count` pixels.
fn analysis_grid(count: u32) -> ((u32, u32), u32) {
    let groups = count.div_ceil(ANALYSIS_GROUP).max(1);
    let x = groups.min(MAX_GROUPS);
    ((x, groups.div_ceil(x)), x * ANALYSIS_GROUP)
}

/// Timestamp queries around the two passes (when the device has `TIMESTAMP_QUERY`).
#[derive(Debug)]
struct Timestamps {
    /// Begin and end of the analysis pass (0, 1) and of the render pass (2, 3).
    set: wgpu::QuerySet,
    /// Resolved ticks: analysis at 0, render at [`wgpu::QUERY_RESOLVE_BUFFER_ALIGNMENT`].
    resolve: wgpu::Buffer,
    /// Nanoseconds per tick.
    period: f32,
}

/// GPU time of the last analysis and render passes, from timestamp queries.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PassTimes {
    /// Milliseconds of the last analysis pass (0 if none ran since timing was enabled).
    pub analysis_ms: f64,
    /// Milliseconds of the last render pass (0 if none ran since timing was enabled).
    pub render_ms: f64,
}

#[derive(Debug)]
struct Target {
    size: (u32, u32),
    texture: wgpu::Texture,
    view: wgpu::TextureView,
}

/// The wgpu backend. See the module docs.
#[derive(Debug)]
pub struct GpuBackend {
    ctx: Arc<GpuContext>,
    analysis: wgpu::ComputePipeline,
    render: wgpu::ComputePipeline,
    analysis_uniform: wgpu::Buffer,
    render_uniform: wgpu::Buffer,
    store: Option<Store>,
    feedback: Option<FeedbackBuffers>,
    target: Option<Target>,
    serial: u64,
    timestamps: Option<Timestamps>,
    /// Samples and GPU seconds of the last collected analysis pass, when timed.
    last_analysis_cost: Option<(usize, f64)>,
    feedback_mode: FeedbackMode,
    /// [`FeedbackMode::Auto`]: pipelined passes still to go before the next wait.
    pipelined_to_go: u32,
    /// Whether [`Backend::analyse`] ran before (the first pass also creates the pipelines and
    /// uploads the whole buffer: its wait says nothing).
    analysed_before: bool,
    /// Upload counters.
    pub stats: UploadStats,
}

fn pipeline(device: &wgpu::Device, source: &str, entry: &str) -> wgpu::ComputePipeline {
    let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(entry),
        source: wgpu::ShaderSource::Wgsl(source.into()),
    });
    device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some(entry),
        layout: None,
        module: &module,
        entry_point: Some(entry),
        compilation_options: Default::default(),
        cache: None,
    })
}

fn uniform_buffer(device: &wgpu::Device, label: &str) -> wgpu::Buffer {
    device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: std::mem::size_of::<FrameUniform>() as u64,
        usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}

/// `len` rounded up to a multiple of 4, at least 4 (bindings cannot be empty).
fn padded(len: u64) -> u64 {
    len.div_ceil(4).max(1) * 4
}

fn channel_slot(c: Channel) -> usize {
    match c {
        Channel::Color => 0,
        Channel::Normal => 1,
        Channel::Density => 2,
    }
}

/// Blocks until the mapping of `slice` completes and returns a copy of its bytes.
fn read_mapped(ctx: &GpuContext, buffer: &wgpu::Buffer, len: u64) -> Result<Vec<u8>, BackendError> {
    let slice = buffer.slice(..len);
    let state = Arc::new(AtomicU8::new(MAP_PENDING));
    let s = state.clone();
    slice.map_async(wgpu::MapMode::Read, move |r| {
        s.store(
            if r.is_ok() { MAP_READY } else { MAP_FAILED },
            Ordering::Release,
        );
    });
    wait_idle(ctx)?;
    if state.load(Ordering::Acquire) != MAP_READY {
        return Err(ctx.fail(BackendError::Device(
            "mapping a read-back buffer failed".into(),
        )));
    }
    let bytes = slice
        .get_mapped_range()
        .map_err(|e| {
            ctx.fail(BackendError::Device(format!(
                "reading a mapped buffer: {e}"
            )))
        })?
        .to_vec();
    buffer.unmap();
    Ok(bytes)
}

/// Waits until the device has finished everything submitted; a fault it reported meanwhile is
/// the error.
fn wait_idle(ctx: &GpuContext) -> Result<(), BackendError> {
    ctx.device
        .poll(wgpu::PollType::wait_indefinitely())
        .map_err(|e| ctx.fail(BackendError::Device(format!("waiting for the GPU: {e}"))))?;
    ctx.check()
}

impl GpuBackend {
    /// Compiles both passes on `ctx`'s device. Buffers come with the first upload.
    pub fn new(ctx: Arc<GpuContext>) -> GpuBackend {
        let device = &ctx.device;
        let analysis = pipeline(device, shaders::ANALYSIS, shaders::ANALYSIS_ENTRY);
        let render = pipeline(device, shaders::RENDER, shaders::RENDER_ENTRY);
        let analysis_uniform = uniform_buffer(device, "analysis uniform");
        let render_uniform = uniform_buffer(device, "render uniform");
        GpuBackend {
            analysis,
            render,
            analysis_uniform,
            render_uniform,
            store: None,
            feedback: None,
            target: None,
            serial: 0,
            timestamps: None,
            last_analysis_cost: None,
            feedback_mode: FeedbackMode::default(),
            pipelined_to_go: 0,
            analysed_before: false,
            stats: UploadStats::default(),
            ctx,
        }
    }

    /// Sets how [`Backend::analyse`] hands feedback back (default [`FeedbackMode::Auto`]).
    pub fn set_feedback_mode(&mut self, mode: FeedbackMode) {
        self.feedback_mode = mode;
    }

    /// Whether this cycle's [`Backend::analyse`] of a `frame_pixels` frame waits for its pass.
    fn waits(&self, frame_pixels: u64) -> bool {
        match self.feedback_mode {
            FeedbackMode::Wait => true,
            FeedbackMode::Pipelined => false,
            // A software adapter runs the pass on the client's own cores: pipelining overlaps
            // nothing there, so it waits whatever the wait.
            FeedbackMode::Auto => {
                frame_pixels <= WAIT_FRAME_PIXELS_MAX
                    && (self.pipelined_to_go == 0 || self.ctx.is_software())
            }
        }
    }

    /// Whether a pipelined pass is in flight or read back and not yet collected.
    fn pipelined_in_flight(&self) -> bool {
        self.feedback.as_ref().is_some_and(|fb| {
            fb.staging
                .iter()
                .any(|s| matches!(s.state.load(Ordering::Acquire), MAP_PENDING | MAP_READY))
        })
    }

    /// [`Backend::analyse`] waiting for the pass; `judged`: whether a wait over [`WAIT_BELOW`]
    /// makes [`FeedbackMode::Auto`] pipeline (not the first pass's). Only when no pipelined
    /// pass is in flight:
    /// the way from pipelining to waiting first waits for those and hands the newest back
    /// instead of running this cycle's pass (the coverage plans its pixels again). Dropping
    /// them instead, with an empty pass waited for in their place (which the coverage ignores),
    /// left their pixels planned and lost in turn forever: a static view on lavapipe stalled
    /// in 2 of 6 runs.
    fn analyse_waiting(
        &mut self,
        input: &PassInput<'_>,
        pixels: &[u32],
        cycle: u64,
        judged: bool,
        out: &mut Feedback,
    ) -> Result<(), BackendError> {
        if self.pipelined_in_flight() {
            wait_idle(&self.ctx)?;
            return self.collect_feedback(out);
        }
        let start = Instant::now();
        self.analyse_pixels_loaded(
            input.frame,
            input.camera,
            input.analysis.lod_bias,
            pixels,
            cycle,
            out,
        )?;
        let wait = start.elapsed();
        if judged && wait > WAIT_BELOW {
            tracing::debug!(
                cycle,
                wait_ms = wait.as_secs_f64() * 1e3,
                "analysis read-back too slow to wait for: pipelining"
            );
            self.pipelined_to_go = PIPELINE_CYCLES;
        }
        Ok(())
    }

    /// [`GpuBackend::new`] with the passes timed when the device can
    /// ([`enable_pass_timing`](GpuBackend::enable_pass_timing)): the analysis pass's measured
    /// cost then sizes the next passes.
    pub fn timed(ctx: Arc<GpuContext>) -> GpuBackend {
        let mut b = GpuBackend::new(ctx);
        b.enable_pass_timing();
        b
    }

    /// Turns on timestamp queries around both passes if the device supports them (the
    /// benchmark's GPU timings); returns whether it did.
    pub fn enable_pass_timing(&mut self) -> bool {
        if !self
            .ctx
            .device
            .features()
            .contains(wgpu::Features::TIMESTAMP_QUERY)
        {
            return false;
        }
        let device = &self.ctx.device;
        let set = device.create_query_set(&wgpu::QuerySetDescriptor {
            label: Some("pass timestamps"),
            ty: wgpu::QueryType::Timestamp,
            count: 4,
        });
        let resolve = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("pass timestamps"),
            size: 2 * wgpu::QUERY_RESOLVE_BUFFER_ALIGNMENT,
            usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        self.timestamps = Some(Timestamps {
            set,
            resolve,
            period: self.ctx.queue.get_timestamp_period(),
        });
        true
    }

    /// GPU times of the last passes (waits for the GPU); `None` unless
    /// [`enable_pass_timing`](GpuBackend::enable_pass_timing) succeeded.
    pub fn pass_times(&self) -> Result<Option<PassTimes>, BackendError> {
        let Some(ts) = self.timestamps.as_ref() else {
            return Ok(None);
        };
        let bytes = self.read_back(&ts.resolve)?;
        let tick = |at: usize| u64::from_le_bytes(bytes[at..at + 8].try_into().expect("8 bytes"));
        let ms = |base: usize| {
            let (a, b) = (tick(base), tick(base + 8));
            b.saturating_sub(a) as f64 * f64::from(ts.period) * 1e-6
        };
        Ok(Some(PassTimes {
            analysis_ms: ms(0),
            render_ms: ms(wgpu::QUERY_RESOLVE_BUFFER_ALIGNMENT as usize),
        }))
    }

    /// Waits until the GPU has finished everything submitted (benchmarks).
    pub fn finish(&self) -> Result<(), BackendError> {
        wait_idle(&self.ctx)
    }

    /// The device this backend runs on.
    pub fn context(&self) -> &Arc<GpuContext> {
        &self.ctx
    }

    /// Largest bytes one storage binding (and one buffer) may hold on this device.
    pub fn max_binding_bytes(&self) -> u64 {
        self.ctx
            .limits
            .max_storage_buffer_binding_size
            .min(self.ctx.limits.max_buffer_size)
    }

    /// Allocates the GPU arrays for `view` if they are missing or shaped differently; returns
    /// whether it did (then everything must be uploaded).
    fn ensure_store(&mut self, view: &IncoreView<'_>) -> bool {
        let n = view.treelet_nodes.max(1);
        let capacity = (view.nodes.len() / n as usize) as u32;
        let channels: Vec<Channel> = Channel::ALL
            .into_iter()
            .filter(|&c| view.channel(c).is_some())
            .collect();
        let fits = self.store.as_ref().is_some_and(|s| {
            s.capacity == capacity && s.treelet_nodes == n && s.channels == channels
        });
        if fits {
            return false;
        }
        let device = &self.ctx.device;
        let records = u64::from(capacity) * u64::from(n);
        let storage = |label: &str, len: u64| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: padded(len),
                usage: wgpu::BufferUsages::STORAGE
                    | wgpu::BufferUsages::COPY_DST
                    | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            })
        };
        let nodes = storage("nodes", records * std::mem::size_of::<Node>() as u64);
        let mut attributes: [Option<wgpu::Buffer>; 3] = [None, None, None];
        for &c in &channels {
            attributes[channel_slot(c)] = Some(storage(c.name(), records * c.size() as u64));
        }
        self.store = Some(Store {
            capacity,
            treelet_nodes: n,
            nodes,
            attributes,
            dummy: storage("absent channel", 4),
            channels,
        });
        true
    }

    /// Writes bytes `range` of `data` (one CPU array) into `buffer`, widened to 4-byte
    /// alignment (the GPU array is the CPU one padded, so the extra bytes are the same bytes,
    /// or zero past the end). Returns the bytes written.
    fn write(queue: &wgpu::Queue, buffer: &wgpu::Buffer, data: &[u8], start: u64, end: u64) -> u64 {
        let start = start & !3;
        let end = padded(end).min(buffer.size());
        if end <= start {
            return 0;
        }
        let (s, e) = (start as usize, end as usize);
        if e <= data.len() {
            queue.write_buffer(buffer, start, &data[s..e]);
        } else {
            let mut tmp = data[s.min(data.len())..].to_vec();
            tmp.resize(e - s, 0);
            queue.write_buffer(buffer, start, &tmp);
        }
        end - start
    }

    /// Copies slot `ranges` of every array of `view` into the GPU arrays.
    fn write_ranges(&mut self, view: &IncoreView<'_>, ranges: &[std::ops::Range<u32>]) {
        let Some(store) = &self.store else {
            return;
        };
        let n = u64::from(store.treelet_nodes);
        let queue = &self.ctx.queue;
        let mut calls = 0;
        let mut bytes = 0;
        let node_bytes: &[u8] = bytemuck::cast_slice(view.nodes);
        let mut arrays: Vec<(&wgpu::Buffer, &[u8], u64)> =
            vec![(&store.nodes, node_bytes, std::mem::size_of::<Node>() as u64)];
        for &c in &store.channels {
            if let (Some(buffer), Some(data)) =
                (&store.attributes[channel_slot(c)], view.channel(c))
            {
                arrays.push((buffer, data, c.size() as u64));
            }
        }
        for (buffer, data, size) in arrays {
            for r in ranges {
                let per_slot = n * size;
                bytes += Self::write(
                    queue,
                    buffer,
                    data,
                    u64::from(r.start) * per_slot,
                    u64::from(r.end) * per_slot,
                );
                calls += 1;
            }
        }
        self.stats.calls += calls;
        self.stats.bytes += bytes;
        self.stats.last_calls = calls;
        self.stats.last_bytes = bytes;
    }

    /// Makes sure the GPU arrays exist (a full upload after an allocation).
    fn ensure_uploaded(&mut self, view: &IncoreView<'_>) {
        if self.ensure_store(view) {
            self.upload_all(view);
        }
    }

    fn upload_all(&mut self, view: &IncoreView<'_>) {
        let slots = self.store.as_ref().map_or(0, |s| s.capacity);
        let everything = std::iter::once(0..slots).collect::<Vec<_>>();
        self.write_ranges(view, &everything);
        self.stats.full_uploads += 1;
    }

    /// Uploads all of `view` (any incore buffer, not only a [`SlotBuffer`]'s), allocating the
    /// GPU arrays to its shape; the `*_loaded` methods then run on it.
    pub fn load(&mut self, view: &IncoreView<'_>) -> Result<(), BackendError> {
        self.ctx.check()?;
        self.ensure_store(view);
        self.upload_all(view);
        self.ctx.check()
    }

    /// Buffers for a pass over `count` pixels (grown to a power of two, never shrunk).
    fn ensure_feedback(&mut self, count: u32) {
        if self.feedback.as_ref().is_some_and(|f| f.capacity >= count) {
            return;
        }
        let capacity = count.max(1024).next_power_of_two();
        let device = &self.ctx.device;
        let sample_bytes = u64::from(capacity) * std::mem::size_of::<FeedbackSample>() as u64;
        let buffer = |label: &str, size: u64, usage| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size,
                usage,
                mapped_at_creation: false,
            })
        };
        let read = wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST;
        // The pass's ticks are copied behind the samples.
        let staged = sample_bytes + 16;
        let staging = |label: &str| Staging {
            buffer: buffer(label, staged, read),
            state: Arc::new(AtomicU8::new(MAP_IDLE)),
            serial: 0,
            cycle: 0,
            pixels: Vec::new(),
        };
        self.feedback = Some(FeedbackBuffers {
            capacity,
            pixels: buffer(
                "analysis pixels",
                u64::from(capacity) * 4,
                wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            ),
            storage: buffer(
                "feedback",
                sample_bytes,
                wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            ),
            staging: [staging("feedback staging 0"), staging("feedback staging 1")],
            blocking: buffer("feedback staging (blocking)", staged, read),
        });
    }

    /// The uniform of an analysis pass over `count` pixels.
    fn analysis_uniform(
        &self,
        frame: &SceneFrame,
        camera: &Camera,
        lod_bias: f64,
        count: u32,
    ) -> FrameUniform {
        let lod = Lod {
            pixel_angle: camera.pixel_angle(),
            lod_bias,
            max_depth: frame.max_depth,
        };
        let channels = self.store.as_ref().map_or(&[][..], |s| &s.channels[..]);
        let (_, stride) = analysis_grid(count);
        FrameUniform::new(frame, camera, &lod, &Light::default(), channels)
            .with_samples(count, stride)
    }

    /// Encodes the analysis pass over `pixels` into the feedback storage buffer and a copy of
    /// its samples (and ticks) into `staging`.
    fn encode_analysis(&self, u: &FrameUniform, pixels: &[u32], staging: &wgpu::Buffer) {
        let (Some(store), Some(fb)) = (&self.store, &self.feedback) else {
            return;
        };
        let queue = &self.ctx.queue;
        queue.write_buffer(&self.analysis_uniform, 0, bytemuck::bytes_of(u));
        queue.write_buffer(&fb.pixels, 0, bytemuck::cast_slice(pixels));
        let entries = [
            wgpu::BindGroupEntry {
                binding: 0,
                resource: self.analysis_uniform.as_entire_binding(),
            },
            wgpu::BindGroupEntry {
                binding: 1,
                resource: store.nodes.as_entire_binding(),
            },
            wgpu::BindGroupEntry {
                binding: 2,
                resource: fb.storage.as_entire_binding(),
            },
            wgpu::BindGroupEntry {
                binding: 3,
                resource: fb.pixels.as_entire_binding(),
            },
        ];
        let (groups, _) = analysis_grid(pixels.len() as u32);
        let mut enc = self.encode_pass(Pass::Analysis, &entries, groups);
        let bytes = pixels.len() as u64 * std::mem::size_of::<FeedbackSample>() as u64;
        if bytes > 0 {
            enc.copy_buffer_to_buffer(&fb.storage, 0, staging, 0, bytes);
        }
        if let Some(t) = &self.timestamps {
            enc.copy_buffer_to_buffer(&t.resolve, 0, staging, staging.size() - 16, 16);
        }
        self.ctx.queue.submit([enc.finish()]);
    }

    /// Decodes a feedback read-back of `pixels` into `out`; returns the pass's GPU seconds when
    /// it was timed.
    fn fill_feedback(
        &self,
        bytes: &[u8],
        cycle: u64,
        pixels: &[u32],
        out: &mut Feedback,
    ) -> Option<f64> {
        let count = pixels.len();
        out.cycle = cycle;
        out.pixels.clear();
        out.pixels.extend_from_slice(pixels);
        out.samples.clear();
        out.samples
            .extend_from_slice(bytemuck::cast_slice::<u8, FeedbackSample>(
                &bytes[..count * std::mem::size_of::<FeedbackSample>()],
            ));
        let ts = self.timestamps.as_ref()?;
        let tail = &bytes[bytes.len() - 16..];
        let tick = |at: usize| u64::from_le_bytes(tail[at..at + 8].try_into().expect("8 bytes"));
        let ticks = tick(8).saturating_sub(tick(0));
        Some(ticks as f64 * f64::from(ts.period) * 1e-9)
    }

    /// The analysis pass of `cycle`, waiting for its result (not pipelined): what
    /// [`Backend::analyse`] returns one cycle later.
    pub fn analyse_blocking(
        &mut self,
        slots: &SlotBuffer,
        frame: &SceneFrame,
        camera: &Camera,
        config: &AnalysisConfig,
        cycle: u64,
        out: &mut Feedback,
    ) -> Result<(), BackendError> {
        self.ctx.check()?;
        self.ensure_uploaded(&slots.view());
        self.analyse_loaded(frame, camera, config, cycle, out)
    }

    /// [`GpuBackend::analyse_blocking`] on what was last [`load`](GpuBackend::load)ed or
    /// uploaded.
    pub fn analyse_loaded(
        &mut self,
        frame: &SceneFrame,
        camera: &Camera,
        config: &AnalysisConfig,
        cycle: u64,
        out: &mut Feedback,
    ) -> Result<(), BackendError> {
        let pixels = grid_pixels(camera.width, camera.height, config.ratio, cycle);
        self.analyse_pixels_loaded(frame, camera, config.lod_bias, &pixels, cycle, out)
    }

    /// The analysis pass of `cycle` over `pixels` on what was last loaded or uploaded, waiting
    /// for its result.
    pub fn analyse_pixels_loaded(
        &mut self,
        frame: &SceneFrame,
        camera: &Camera,
        lod_bias: f64,
        pixels: &[u32],
        cycle: u64,
        out: &mut Feedback,
    ) -> Result<(), BackendError> {
        self.ctx.check()?;
        let count = pixels.len() as u32;
        let u = self.analysis_uniform(frame, camera, lod_bias, count);
        self.ensure_feedback(count);
        let fb = self.feedback.as_ref().expect("feedback buffers");
        self.encode_analysis(&u, pixels, &fb.blocking);
        let len = fb.blocking.size();
        let bytes = read_mapped(&self.ctx, &fb.blocking, len)?;
        let seconds = self.fill_feedback(&bytes, cycle, pixels, out);
        self.last_analysis_cost = seconds.map(|t| (pixels.len(), t));
        Ok(())
    }

    /// Collects completed read-backs: the newest goes to `out`, all are released.
    fn collect_feedback(&mut self, out: &mut Feedback) -> Result<(), BackendError> {
        self.ctx.check()?;
        let Some(fb) = &self.feedback else {
            return Ok(());
        };
        let mut newest: Option<usize> = None;
        for (i, s) in fb.staging.iter().enumerate() {
            match s.state.load(Ordering::Acquire) {
                MAP_READY if newest.is_none_or(|n| fb.staging[n].serial < s.serial) => {
                    newest = Some(i);
                }
                MAP_FAILED => s.state.store(MAP_IDLE, Ordering::Release),
                _ => {}
            }
        }
        if let Some(i) = newest {
            let s = &fb.staging[i];
            let bytes = s
                .buffer
                .slice(..)
                .get_mapped_range()
                .map_err(|e| {
                    self.ctx
                        .fail(BackendError::Device(format!("reading the feedback: {e}")))
                })?
                .to_vec();
            let seconds = self.fill_feedback(&bytes, s.cycle, &s.pixels, out);
            self.last_analysis_cost = seconds.map(|t| (s.pixels.len(), t));
        }
        for s in &fb.staging {
            if s.state.load(Ordering::Acquire) == MAP_READY {
                s.buffer.unmap();
                s.state.store(MAP_IDLE, Ordering::Release);
            }
        }
        Ok(())
    }

    /// Creates or resizes the render target to `size`.
    fn ensure_target(&mut self, size: (u32, u32)) {
        if self.target.as_ref().is_some_and(|t| t.size == size) {
            return;
        }
        let texture = self.ctx.device.create_texture(&wgpu::TextureDescriptor {
            label: Some("render target"),
            size: wgpu::Extent3d {
                width: size.0,
                height: size.1,
                depth_or_array_layers: 1,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: wgpu::TextureFormat::Rgba8Unorm,
            usage: wgpu::TextureUsages::STORAGE_BINDING
                | wgpu::TextureUsages::TEXTURE_BINDING
                | wgpu::TextureUsages::COPY_SRC,
            view_formats: &[],
        });
        let view = texture.create_view(&Default::default());
        self.target = Some(Target {
            size,
            texture,
            view,
        });
    }

    /// Renders into the target texture (created or resized to the camera's frame), and copies
    /// it into `readback` (a buffer and its row pitch) when given.
    fn encode_render(
        &mut self,
        frame: &SceneFrame,
        camera: &Camera,
        lod_bias: f64,
        light: &Light,
        readback: Option<(&wgpu::Buffer, u32)>,
    ) {
        let size = (camera.width, camera.height);
        self.ensure_target(size);
        let (Some(store), Some(target)) = (&self.store, &self.target) else {
            return;
        };
        let lod = Lod {
            pixel_angle: camera.pixel_angle(),
            lod_bias,
            max_depth: frame.max_depth,
        };
        let u = FrameUniform::new(frame, camera, &lod, light, &store.channels);
        self.ctx
            .queue
            .write_buffer(&self.render_uniform, 0, bytemuck::bytes_of(&u));
        let attr = |c: Channel| {
            store.attributes[channel_slot(c)]
                .as_ref()
                .unwrap_or(&store.dummy)
                .as_entire_binding()
        };
        let entries = [
            wgpu::BindGroupEntry {
                binding: 0,
                resource: self.render_uniform.as_entire_binding(),
            },
            wgpu::BindGroupEntry {
                binding: 1,
                resource: store.nodes.as_entire_binding(),
            },
            wgpu::BindGroupEntry {
                binding: 2,
                resource: attr(Channel::Color),
            },
            wgpu::BindGroupEntry {
                binding: 3,
                resource: attr(Channel::Normal),
            },
            wgpu::BindGroupEntry {
                binding: 4,
                resource: attr(Channel::Density),
            },
            wgpu::BindGroupEntry {
                binding: 5,
                resource: wgpu::BindingResource::TextureView(&target.view),
            },
        ];
        let groups = (size.0.div_ceil(8), size.1.div_ceil(8));
        let mut enc = self.encode_pass(Pass::Render, &entries, groups);
        if let Some((buffer, row)) = readback {
            enc.copy_texture_to_buffer(
                wgpu::TexelCopyTextureInfo {
                    texture: &target.texture,
                    mip_level: 0,
                    origin: wgpu::Origin3d::ZERO,
                    aspect: wgpu::TextureAspect::All,
                },
                wgpu::TexelCopyBufferInfo {
                    buffer,
                    layout: wgpu::TexelCopyBufferLayout {
                        offset: 0,
                        bytes_per_row: Some(row),
                        rows_per_image: Some(size.1),
                    },
                },
                wgpu::Extent3d {
                    width: size.0,
                    height: size.1,
                    depth_or_array_layers: 1,
                },
            );
        }
        self.ctx.queue.submit([enc.finish()]);
    }

    /// One compute pass of `pass`'s pipeline over `groups` workgroups with `entries`
    /// bound as group 0, timed when timestamp queries are on, in a new encoder the caller may add
    /// copies to before submitting.
    fn encode_pass(
        &self,
        pass: Pass,
        entries: &[wgpu::BindGroupEntry<'_>],
        groups: (u32, u32),
    ) -> wgpu::CommandEncoder {
        let device = &self.ctx.device;
        let pipeline = match pass {
            Pass::Analysis => &self.analysis,
            Pass::Render => &self.render,
        };
        let bind = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some(pass.label()),
            layout: &pipeline.get_bind_group_layout(0),
            entries,
        });
        let mut enc = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some(pass.label()),
        });
        let first_query = pass.first_query();
        {
            let mut cpass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some(pass.label()),
                timestamp_writes: self.timestamps.as_ref().map(|t| {
                    wgpu::ComputePassTimestampWrites {
                        query_set: &t.set,
                        beginning_of_pass_write_index: Some(first_query),
                        end_of_pass_write_index: Some(first_query + 1),
                    }
                }),
            });
            cpass.set_pipeline(pipeline);
            cpass.set_bind_group(0, &bind, &[]);
            cpass.dispatch_workgroups(groups.0, groups.1, 1);
        }
        if let Some(t) = &self.timestamps {
            enc.resolve_query_set(
                &t.set,
                first_query..first_query + 2,
                &t.resolve,
                pass.resolve_offset(),
            );
        }
        enc
    }

    /// The GPU node array, read back (blocking): `capacity × N` records.
    pub fn read_back_nodes(&self) -> Result<Vec<Node>, BackendError> {
        let Some(store) = &self.store else {
            return Ok(Vec::new());
        };
        let bytes = self.read_back(&store.nodes)?;
        let records = store.capacity as usize * store.treelet_nodes as usize;
        Ok(bytemuck::pod_collect_to_vec(
            &bytes[..records * std::mem::size_of::<Node>()],
        ))
    }

    /// The GPU array of `channel`, read back (blocking), without the padding; `None` when the
    /// channel is not held.
    pub fn read_back_attributes(&self, channel: Channel) -> Result<Option<Vec<u8>>, BackendError> {
        let Some(store) = self.store.as_ref() else {
            return Ok(None);
        };
        let Some(buffer) = store.attributes[channel_slot(channel)].as_ref() else {
            return Ok(None);
        };
        let mut bytes = self.read_back(buffer)?;
        bytes.truncate(store.capacity as usize * store.treelet_nodes as usize * channel.size());
        Ok(Some(bytes))
    }

    fn read_back(&self, buffer: &wgpu::Buffer) -> Result<Vec<u8>, BackendError> {
        self.ctx.check()?;
        let device = &self.ctx.device;
        let staging = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("read back"),
            size: buffer.size(),
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut enc = device.create_command_encoder(&Default::default());
        enc.copy_buffer_to_buffer(buffer, 0, &staging, 0, buffer.size());
        self.ctx.queue.submit([enc.finish()]);
        read_mapped(&self.ctx, &staging, buffer.size())
    }
}

impl Backend for GpuBackend {
    fn name(&self) -> String {
        format!("wgpu {}", self.ctx.describe())
    }

    fn max_slots(&self, treelet_nodes: u32, channels: &[Channel]) -> u32 {
        let widest = channels
            .iter()
            .map(|c| c.size() as u64)
            .chain([std::mem::size_of::<Node>() as u64])
            .max()
            .unwrap_or(8);
        let per_slot = u64::from(treelet_nodes.max(1)) * widest;
        (self.max_binding_bytes() / per_slot).min(u64::from(u32::MAX)) as u32
    }

    fn analyse(
        &mut self,
        input: &PassInput<'_>,
        pixels: &[u32],
        cycle: u64,
        out: &mut Feedback,
    ) -> Result<(), BackendError> {
        self.ctx.check()?;
        self.ensure_uploaded(&input.slots.view());
        let frame_pixels = u64::from(input.camera.width) * u64::from(input.camera.height);
        let judged = std::mem::replace(&mut self.analysed_before, true);
        if self.waits(frame_pixels) {
            return self.analyse_waiting(input, pixels, cycle, judged, out);
        }
        self.pipelined_to_go = self.pipelined_to_go.saturating_sub(1);
        let device = &self.ctx.device;
        // Non-blocking: runs the callbacks of whatever has completed.
        let _ = device.poll(wgpu::PollType::Poll);
        self.collect_feedback(out)?;
        if pixels.is_empty() {
            return Ok(());
        }
        let count = pixels.len() as u32;
        let u = self.analysis_uniform(input.frame, input.camera, input.analysis.lod_bias, count);
        // Growing the buffers drops read-backs in flight: only when both staging buffers are
        // idle (otherwise this cycle's pass is skipped and its pixels planned again).
        let idle = |fb: &FeedbackBuffers| {
            fb.staging
                .iter()
                .all(|s| s.state.load(Ordering::Acquire) == MAP_IDLE)
        };
        if self
            .feedback
            .as_ref()
            .is_none_or(|f| f.capacity >= count || idle(f))
        {
            self.ensure_feedback(count);
        }
        let fb = self.feedback.as_ref().expect("feedback buffers");
        if fb.capacity < count {
            return Ok(());
        }
        let Some(i) = fb
            .staging
            .iter()
            .position(|s| s.state.load(Ordering::Acquire) == MAP_IDLE)
        else {
            return Ok(());
        };
        self.encode_analysis(&u, pixels, &fb.staging[i].buffer);
        self.serial += 1;
        let serial = self.serial;
        let fb = self.feedback.as_mut().expect("feedback buffers");
        let s = &mut fb.staging[i];
        s.serial = serial;
        s.cycle = cycle;
        s.pixels.clear();
        s.pixels.extend_from_slice(pixels);
        s.state.store(MAP_PENDING, Ordering::Release);
        let state = s.state.clone();
        s.buffer.slice(..).map_async(wgpu::MapMode::Read, move |r| {
            state.store(
                if r.is_ok() { MAP_READY } else { MAP_FAILED },
                Ordering::Release,
            );
        });
        let _ = self.ctx.device.poll(wgpu::PollType::Poll);
        self.ctx.check()
    }

    fn upload(&mut self, slots: &SlotBuffer, plan: &UploadPlan) -> Result<(), BackendError> {
        self.ctx.check()?;
        let view = slots.view();
        if self.ensure_store(&view) {
            self.upload_all(&view);
        } else {
            self.write_ranges(&view, &plan.ranges);
        }
        self.ctx.check()
    }

    fn render_in_place(&mut self, input: &PassInput<'_>) -> Result<bool, BackendError> {
        self.ctx.check()?;
        self.ensure_uploaded(&input.slots.view());
        self.encode_render(
            input.frame,
            input.camera,
            input.analysis.lod_bias,
            input.light,
            None,
        );
        self.ctx.check()?;
        Ok(true)
    }

    fn render(&mut self, input: &PassInput<'_>) -> Result<Image, BackendError> {
        self.ctx.check()?;
        self.ensure_uploaded(&input.slots.view());
        self.render_loaded(
            input.frame,
            input.camera,
            input.analysis.lod_bias,
            input.light,
        )
    }

    fn analysis_cost(&self) -> Option<(usize, f64)> {
        self.last_analysis_cost
    }

    fn as_any(&self) -> &dyn std::any::Any {
        self
    }
}

impl GpuBackend {
    /// The target [`Backend::render_in_place`] drew into, once it has drawn (the window viewer
    /// samples it).
    pub fn target_view(&self) -> Option<&wgpu::TextureView> {
        self.target.as_ref().map(|t| &t.view)
    }

    /// [`Backend::render`] on what was last [`load`](GpuBackend::load)ed or uploaded.
    pub fn render_loaded(
        &mut self,
        frame: &SceneFrame,
        camera: &Camera,
        lod_bias: f64,
        light: &Light,
    ) -> Result<Image, BackendError> {
        self.ctx.check()?;
        let (w, h) = (camera.width, camera.height);
        let row = (w * 4).div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT)
            * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
        let buffer = self.ctx.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("render read back"),
            size: u64::from(row) * u64::from(h),
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        self.encode_render(frame, camera, lod_bias, light, Some((&buffer, row)));
        let bytes = read_mapped(&self.ctx, &buffer, buffer.size())?;
        let mut img = Image::new(w, h);
        let tight = w as usize * 4;
        for (y, dst) in img.rgba.chunks_exact_mut(tight).enumerate() {
            let src = y * row as usize;
            dst.copy_from_slice(&bytes[src..src + tight]);
        }
        Ok(img)
    }
}

/// The two compute passes, named like their pipelines, entry points and CPU twins.
#[derive(Clone, Copy, Debug)]
enum Pass {
    Analysis,
    Render,
}

impl Pass {
    /// Pipeline, entry point and label.
    fn label(self) -> &'static str {
        match self {
            Pass::Analysis => shaders::ANALYSIS_ENTRY,
            Pass::Render => shaders::RENDER_ENTRY,
        }
    }

    /// The pass's begin timestamp query (its end is the next one).
    fn first_query(self) -> u32 {
        match self {
            Pass::Analysis => 0,
            Pass::Render => 2,
        }
    }

    /// Where the pass's two resolved timestamps go in the resolve buffer.
    fn resolve_offset(self) -> u64 {
        match self {
            Pass::Analysis => 0,
            Pass::Render => wgpu::QUERY_RESOLVE_BUFFER_ALIGNMENT,
        }
    }
}
