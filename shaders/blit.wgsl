// The window viewer's only render pass: one fullscreen triangle that draws the frame texture
// (what the renderer produced, `rgba8unorm` holding sRGB-encoded bytes, alpha 0 where a ray
// hit nothing) over a dark background, then the statistics overlay panel on top.
//
// Compositing happens on the encoded values, exactly as the CPU renderer's bytes mean them,
// so on a UNORM surface every covered pixel reaches the window byte for byte. On an *Srgb
// surface (`params.decode_srgb == 1`) the result is decoded to linear first, because the
// hardware encodes again when it stores; the round trip is within one step of 8 bits.
//
// The frame is sampled with `textureLoad` (nearest, no filtering): when the frame has the
// surface's size each window pixel is exactly one frame pixel.

struct Params {
    // Surface (window) size in pixels.
    surface_size: vec2<f32>,
    // Frame texture size in pixels.
    frame_size: vec2<f32>,
    // Overlay panel: x, y, width, height in surface pixels; width 0 draws none.
    overlay_rect: vec4<f32>,
    // Background where the frame's alpha is 0: sRGB-encoded, 0..1.
    background: vec4<f32>,
    // 1 when the surface format is *Srgb.
    decode_srgb: u32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
}

@group(0) @binding(0) var frame: texture_2d<f32>;
@group(0) @binding(1) var overlay: texture_2d<f32>;
@group(0) @binding(2) var<uniform> params: Params;

@vertex
fn vs_main(@builtin(vertex_index) index: u32) -> @builtin(position) vec4<f32> {
    // (-1, 1), (3, 1), (-1, -3): one triangle covering the whole viewport.
    let x = f32((index << 1u) & 2u);
    let y = f32(index & 2u);
    return vec4<f32>(x * 2.0 - 1.0, 1.0 - y * 2.0, 0.0, 1.0);
}

fn srgb_to_linear(c: vec3<f32>) -> vec3<f32> {
    let low = c / 12.92;
    let high = pow((c + vec3<f32>(0.055)) / 1.055, vec3<f32>(2.4));
    return select(high, low, c <= vec3<f32>(0.04045));
}

@fragment
fn fs_main(@builtin(position) position: vec4<f32>) -> @location(0) vec4<f32> {
    let p = position.xy;
    let frame_max = vec2<i32>(params.frame_size) - vec2<i32>(1);
    let texel = vec2<i32>(floor(p * params.frame_size / params.surface_size));
    let scene = textureLoad(frame, clamp(texel, vec2<i32>(0), frame_max), 0);
    var colour = mix(params.background.rgb, scene.rgb, scene.a);

    let r = params.overlay_rect;
    if r.z > 0.0 && p.x >= r.x && p.y >= r.y && p.x < r.x + r.z && p.y < r.y + r.w {
        let o = textureLoad(overlay, vec2<i32>(floor(p - r.xy)), 0);
        colour = mix(colour, o.rgb, o.a);
    }
    if params.decode_srgb != 0u {
        colour = srgb_to_linear(colour);
    }
    return vec4<f32>(colour, 1.0);
}
