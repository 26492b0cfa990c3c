//! The viewer's GPU side that is not the renderer: the blit pass (`shaders/blit.wgsl`) that
//! draws the frame texture and the overlay panel to the window surface, the frame texture the
//! CPU fallback uploads into, and reading an `rgba8unorm` texture back into an [`Image`]
//! (screenshots).
//!
//! **sRGB.** Frames are `rgba8unorm` textures holding sRGB-*encoded* bytes (what the CPU
//! renderer writes and the GPU backend's target holds). [`choose_surface_format`] prefers a
//! non-sRGB (UNORM) surface format, so the encoded values are stored unchanged and a covered
//! window pixel equals the renderer's byte exactly. Only when a surface offers nothing but
//! `*Srgb` formats does the shader decode to linear before the hardware re-encodes (±1 step).

use std::num::NonZeroU64;

use bytemuck::{Pod, Zeroable};

use arbor_client_core::image::Image;

use super::overlay::OverlayImage;

/// The blit shader's source.
pub const SHADER: &str = include_str!("../../../shaders/blit.wgsl");

/// Where the frame's alpha is 0: a dark blue-grey, sRGB-encoded.
pub const BACKGROUND: [u8; 3] = [22, 24, 30];

/// Offset of the overlay panel from the window's top-left corner, pixels.
pub const OVERLAY_MARGIN: u32 = 6;

/// The format of frame and overlay textures.
pub const FRAME_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;

/// The surface format to draw to and whether the shader must decode sRGB first: the first
/// UNORM 8-bit format offered, else the first format (decoding if it is `*Srgb`). `None` when
/// nothing is offered.
pub fn choose_surface_format(
    formats: &[wgpu::TextureFormat],
) -> Option<(wgpu::TextureFormat, bool)> {
    use wgpu::TextureFormat as F;
    formats
        .iter()
        .copied()
        .find(|f| matches!(f, F::Bgra8Unorm | F::Rgba8Unorm))
        .or_else(|| formats.first().copied())
        .map(|f| (f, f.is_srgb()))
}

/// The blit shader's uniforms (layout of `Params` in `blit.wgsl`: 64 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct Params {
    pub surface_size: [f32; 2],
    pub frame_size: [f32; 2],
    pub overlay_rect: [f32; 4],
    pub background: [f32; 4],
    pub decode_srgb: u32,
    pub pad: [u32; 3],
}

impl Params {
    /// Uniforms for a `surface` sized window showing a `frame` sized texture, with an overlay
    /// panel of `overlay` size at [`OVERLAY_MARGIN`] (`None`: hidden).
    pub fn new(
        surface: (u32, u32),
        frame: (u32, u32),
        overlay: Option<(u32, u32)>,
        decode_srgb: bool,
    ) -> Self {
        let m = OVERLAY_MARGIN as f32;
        Self {
            surface_size: [surface.0.max(1) as f32, surface.1.max(1) as f32],
            frame_size: [frame.0.max(1) as f32, frame.1.max(1) as f32],
            overlay_rect: overlay.map_or([0.0; 4], |(w, h)| [m, m, w as f32, h as f32]),
            background: [
                f32::from(BACKGROUND[0]) / 255.0,
                f32::from(BACKGROUND[1]) / 255.0,
                f32::from(BACKGROUND[2]) / 255.0,
                1.0,
            ],
            decode_srgb: u32::from(decode_srgb),
            pad: [0; 3],
        }
    }
}

/// The blit pipeline and the overlay panel's texture.
#[derive(Debug)]
pub struct Blit {
    pipeline: wgpu::RenderPipeline,
    layout: wgpu::BindGroupLayout,
    params: wgpu::Buffer,
    overlay: wgpu::Texture,
    overlay_view: wgpu::TextureView,
    overlay_size: (u32, u32),
    decode_srgb: bool,
}

impl Blit {
    /// A pipeline drawing to `surface_format`, with an overlay texture of `overlay_size`.
    pub fn new(
        device: &wgpu::Device,
        surface_format: wgpu::TextureFormat,
        decode_srgb: bool,
        overlay_size: (u32, u32),
    ) -> Self {
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("blit"),
            source: wgpu::ShaderSource::Wgsl(SHADER.into()),
        });
        let texture_entry = |binding| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::FRAGMENT,
            ty: wgpu::BindingType::Texture {
                sample_type: wgpu::TextureSampleType::Float { filterable: false },
                view_dimension: wgpu::TextureViewDimension::D2,
                multisampled: false,
            },
            count: None,
        };
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("blit"),
            entries: &[
                texture_entry(0),
                texture_entry(1),
                wgpu::BindGroupLayoutEntry {
                    binding: 2,
                    visibility: wgpu::ShaderStages::FRAGMENT,
                    ty: wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Uniform,
                        has_dynamic_offset: false,
                        min_binding_size: NonZeroU64::new(std::mem::size_of::<Params>() as u64),
                    },
                    count: None,
                },
            ],
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("blit"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let pipeline = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("blit"),
            layout: Some(&pipeline_layout),
            vertex: wgpu::VertexState {
                module: &module,
                entry_point: Some("vs_main"),
                compilation_options: Default::default(),
                buffers: &[],
            },
            primitive: wgpu::PrimitiveState::default(),
            depth_stencil: None,
            multisample: wgpu::MultisampleState::default(),
            fragment: Some(wgpu::FragmentState {
                module: &module,
                entry_point: Some("fs_main"),
                compilation_options: Default::default(),
                targets: &[Some(wgpu::ColorTargetState {
                    format: surface_format,
                    blend: None,
                    write_mask: wgpu::ColorWrites::ALL,
                })],
            }),
            multiview_mask: None,
            cache: None,
        });
        let params = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("blit params"),
            size: std::mem::size_of::<Params>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let overlay = texture(
            device,
            "overlay",
            overlay_size,
            wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
        );
        let overlay_view = overlay.create_view(&wgpu::TextureViewDescriptor::default());
        Self {
            pipeline,
            layout,
            params,
            overlay,
            overlay_view,
            overlay_size,
            decode_srgb,
        }
    }

    /// Replaces the overlay panel's pixels; an image of another size is ignored (the panel
    /// has a fixed size, see [`Overlay::panel_size`](super::overlay::Overlay::panel_size)).
    pub fn set_overlay(&self, queue: &wgpu::Queue, image: &OverlayImage) {
        if (image.width, image.height) != self.overlay_size {
            return;
        }
        write_rgba(queue, &self.overlay, image.width, image.height, &image.rgba);
    }

    /// Records the pass drawing `frame` (and the overlay, when `show_overlay`) to `target`, a
    /// view of a surface texture of the surface format.
    pub fn draw(
        &self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        encoder: &mut wgpu::CommandEncoder,
        target: &wgpu::TextureView,
        frame: &wgpu::TextureView,
        show_overlay: bool,
    ) {
        let frame_size = frame.texture().size();
        let surface = target.texture().size();
        let params = Params::new(
            (surface.width, surface.height),
            (frame_size.width, frame_size.height),
            show_overlay.then_some(self.overlay_size),
            self.decode_srgb,
        );
        queue.write_buffer(&self.params, 0, bytemuck::bytes_of(&params));
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("blit"),
            layout: &self.layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: wgpu::BindingResource::TextureView(frame),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::TextureView(&self.overlay_view),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: self.params.as_entire_binding(),
                },
            ],
        });
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("blit"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: target,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    load: wgpu::LoadOp::Clear(wgpu::Color::BLACK),
                    store: wgpu::StoreOp::Store,
                },
            })],
            depth_stencil_attachment: None,
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &bind_group, &[]);
        pass.draw(0..3, 0..1);
    }
}

/// The frame texture of the CPU fallback: each cycle's [`Image`] is uploaded into it.
#[derive(Debug)]
pub struct FrameTexture {
    texture: wgpu::Texture,
    view: wgpu::TextureView,
}

impl FrameTexture {
    pub fn new(device: &wgpu::Device, width: u32, height: u32) -> Self {
        let texture = texture(
            device,
            "frame",
            (width, height),
            wgpu::TextureUsages::TEXTURE_BINDING
                | wgpu::TextureUsages::COPY_DST
                | wgpu::TextureUsages::COPY_SRC,
        );
        let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        Self { texture, view }
    }

    pub fn size(&self) -> (u32, u32) {
        (self.texture.width(), self.texture.height())
    }

    pub fn view(&self) -> &wgpu::TextureView {
        &self.view
    }

    /// Uploads `image`, which must have the texture's size (else nothing happens).
    pub fn upload(&self, queue: &wgpu::Queue, image: &Image) {
        if (image.width, image.height) == self.size() {
            write_rgba(queue, &self.texture, image.width, image.height, &image.rgba);
        }
    }
}

fn texture(
    device: &wgpu::Device,
    label: &str,
    (width, height): (u32, u32),
    usage: wgpu::TextureUsages,
) -> wgpu::Texture {
    device.create_texture(&wgpu::TextureDescriptor {
        label: Some(label),
        size: wgpu::Extent3d {
            width: width.max(1),
            height: height.max(1),
            depth_or_array_layers: 1,
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format: FRAME_FORMAT,
        usage,
        view_formats: &[],
    })
}

fn write_rgba(queue: &wgpu::Queue, texture: &wgpu::Texture, width: u32, height: u32, rgba: &[u8]) {
    queue.write_texture(
        wgpu::TexelCopyTextureInfo {
            texture,
            mip_level: 0,
            origin: wgpu::Origin3d::ZERO,
            aspect: wgpu::TextureAspect::All,
        },
        rgba,
        wgpu::TexelCopyBufferLayout {
            offset: 0,
            bytes_per_row: Some(width * 4),
            rows_per_image: Some(height),
        },
        wgpu::Extent3d {
            width,
            height,
            depth_or_array_layers: 1,
        },
    );
}

/// Why a read-back failed.
#[derive(Debug, thiserror::Error)]
pub enum ReadBackError {
    #[error("texture format {0:?} is not rgba8unorm")]
    Format(wgpu::TextureFormat),
    #[error("texture lacks COPY_SRC usage")]
    Usage,
    #[error("mapping the read-back buffer: {0}")]
    Map(String),
}

/// Copies an `rgba8unorm` texture (with `COPY_SRC`) back into an [`Image`], waiting for the GPU.
pub fn read_back(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    texture: &wgpu::Texture,
) -> Result<Image, ReadBackError> {
    if texture.format() != FRAME_FORMAT {
        return Err(ReadBackError::Format(texture.format()));
    }
    if !texture.usage().contains(wgpu::TextureUsages::COPY_SRC) {
        return Err(ReadBackError::Usage);
    }
    let (width, height) = (texture.width(), texture.height());
    let row = width * 4;
    let padded =
        row.div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT) * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
    let buffer = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("read-back"),
        size: u64::from(padded) * u64::from(height),
        usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
        mapped_at_creation: false,
    });
    let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
        label: Some("read-back"),
    });
    encoder.copy_texture_to_buffer(
        texture.as_image_copy(),
        wgpu::TexelCopyBufferInfo {
            buffer: &buffer,
            layout: wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(padded),
                rows_per_image: Some(height),
            },
        },
        texture.size(),
    );
    queue.submit([encoder.finish()]);
    let (tx, rx) = std::sync::mpsc::channel();
    buffer.map_async(wgpu::MapMode::Read, .., move |r| {
        let _ = tx.send(r);
    });
    device
        .poll(wgpu::PollType::wait_indefinitely())
        .map_err(|e| ReadBackError::Map(e.to_string()))?;
    rx.recv()
        .map_err(|e| ReadBackError::Map(e.to_string()))?
        .map_err(|e| ReadBackError::Map(e.to_string()))?;
    let mut image = Image::new(width, height);
    {
        let data = buffer
            .get_mapped_range(..)
            .map_err(|e| ReadBackError::Map(e.to_string()))?;
        for (y, out) in image.rgba.chunks_exact_mut(row as usize).enumerate() {
            let start = y * padded as usize;
            out.copy_from_slice(&data[start..start + row as usize]);
        }
    }
    buffer.unmap();
    Ok(image)
}

#[cfg(test)]
mod tests {
    use super::*;
    use wgpu::TextureFormat as F;

    #[test]
    fn the_shader_parses_and_validates() {
        let module = wgpu::naga::front::wgsl::parse_str(SHADER).expect("blit.wgsl parses");
        wgpu::naga::valid::Validator::new(
            wgpu::naga::valid::ValidationFlags::all(),
            wgpu::naga::valid::Capabilities::empty(),
        )
        .validate(&module)
        .expect("blit.wgsl validates");
        for entry in ["vs_main", "fs_main"] {
            assert!(
                module.entry_points.iter().any(|e| e.name == entry),
                "{entry}"
            );
        }
    }

    #[test]
    fn params_match_the_shader_layout() {
        assert_eq!(std::mem::size_of::<Params>(), 64);
        let p = Params::new((256, 192), (128, 96), Some((340, 150)), true);
        assert_eq!(p.surface_size, [256.0, 192.0]);
        assert_eq!(p.frame_size, [128.0, 96.0]);
        let m = OVERLAY_MARGIN as f32;
        assert_eq!(p.overlay_rect, [m, m, 340.0, 150.0]);
        assert_eq!(p.decode_srgb, 1);
        assert_eq!(p.background[3], 1.0);
        assert_eq!(
            Params::new((0, 0), (0, 0), None, false).overlay_rect,
            [0.0; 4]
        );
        assert_eq!(
            Params::new((0, 0), (0, 0), None, false).surface_size,
            [1.0, 1.0]
        );
    }

    #[test]
    fn a_unorm_surface_format_is_preferred_so_bytes_pass_through() {
        assert_eq!(
            choose_surface_format(&[F::Bgra8UnormSrgb, F::Bgra8Unorm]),
            Some((F::Bgra8Unorm, false))
        );
        assert_eq!(
            choose_surface_format(&[F::Rgba8UnormSrgb, F::Rgba8Unorm]),
            Some((F::Rgba8Unorm, false))
        );
        assert_eq!(
            choose_surface_format(&[F::Bgra8UnormSrgb]),
            Some((F::Bgra8UnormSrgb, true))
        );
        assert_eq!(
            choose_surface_format(&[F::Rgb10a2Unorm]),
            Some((F::Rgb10a2Unorm, false))
        );
        assert_eq!(choose_surface_format(&[]), None);
    }
}
