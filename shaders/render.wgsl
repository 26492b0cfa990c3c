// The render pass: `client/src/render.rs`, GPU twin. Appended to `traverse.wgsl`. One
// invocation per pixel: the ray through the pixel centre, the nearest voxel it stops at,
// shaded like `render::shade` (albedo from colour, else density, else neutral grey; normal
// from the attribute, else the entry face; two-sided Lambert plus ambient in linear space;
// sRGB encoded to 8 bits with the CPU's rounding) and written to an `rgba8unorm` storage
// texture; misses are transparent black.
//
// The attribute arrays are the CPU slot buffer's bytes, copied byte for byte into `u32` words
// (little endian, padded to 4 bytes), and unpacked here: colour is 3 bytes per node and so
// straddles words, a normal is one word (two u16), a density half a word.

@group(0) @binding(2) var<storage, read> color: array<u32>;
@group(0) @binding(3) var<storage, read> normal: array<u32>;
@group(0) @binding(4) var<storage, read> density: array<u32>;
@group(0) @binding(5) var target_image: texture_storage_2d<rgba8unorm, write>;

const NEUTRAL_ALBEDO: f32 = 0.6;

fn color_byte(i: u32) -> u32 {
    return (color[i >> 2u] >> ((i & 3u) * 8u)) & 0xffu;
}

fn srgb_to_linear(c: f32) -> f32 {
    if c <= 0.04045 {
        return c / 12.92;
    }
    return pow((c + 0.055) / 1.055, 2.4);
}

// The 8-bit sRGB code of a linear value, as `render::linear_to_srgb8` rounds it.
fn linear_to_srgb8(x: f32) -> u32 {
    let c = clamp(x, 0.0, 1.0);
    var s: f32;
    if c <= 0.0031308 {
        s = c * 12.92;
    } else {
        s = 1.055 * pow(c, 1.0 / 2.4) - 0.055;
    }
    return u32(clamp(s * 255.0 + 0.5, 0.0, 255.0));
}

// `arbor_proto::attribute::oct_decode`.
fn oct_decode(u: u32, v: u32) -> vec3<f32> {
    var x = f32(u) / 65535.0 * 2.0 - 1.0;
    var y = f32(v) / 65535.0 * 2.0 - 1.0;
    let z = 1.0 - abs(x) - abs(y);
    if z < 0.0 {
        let ox = x;
        let oy = y;
        x = (1.0 - abs(oy)) * select(-1.0, 1.0, ox >= 0.0);
        y = (1.0 - abs(ox)) * select(-1.0, 1.0, oy >= 0.0);
    }
    let len = sqrt(x * x + y * y + z * z);
    return vec3<f32>(x / len, y / len, z / len);
}

fn shade(hit: Hit, dir: vec3<f32>) -> vec4<u32> {
    let flags = frame.flags.x;
    var albedo = vec3<f32>(NEUTRAL_ALBEDO);
    if (flags & FLAG_COLOR) != 0u {
        let b = hit.node * 3u;
        albedo = vec3<f32>(
            srgb_to_linear(f32(color_byte(b)) / 255.0),
            srgb_to_linear(f32(color_byte(b + 1u)) / 255.0),
            srgb_to_linear(f32(color_byte(b + 2u)) / 255.0),
        );
    } else if (flags & FLAG_DENSITY) != 0u {
        let w = density[hit.node >> 1u] >> ((hit.node & 1u) * 16u);
        albedo = vec3<f32>(f32(w & 0xffffu) / 65535.0);
    }
    var n = vec3<f32>(0.0);
    if (flags & FLAG_NORMAL) != 0u {
        let w = normal[hit.node];
        n = oct_decode(w & 0xffffu, w >> 16u);
    } else {
        n[min(hit.entry_axis, 2u)] = hit.entry_sign;
    }
    // Two-sided: turn the normal towards the viewer, then Lambert.
    let len = length(n);
    if len > 0.0 {
        n = n / len;
    } else {
        n = vec3<f32>(0.0);
    }
    if dot(n, dir) > 0.0 {
        n = -n;
    }
    let diffuse = max(dot(n, frame.light.xyz), 0.0);
    let ambient = frame.light.w;
    let k = ambient + (1.0 - ambient) * diffuse;
    return vec4<u32>(linear_to_srgb8(albedo.x * k), linear_to_srgb8(albedo.y * k), linear_to_srgb8(albedo.z * k), 255u);
}

@compute @workgroup_size(8, 8, 1)
fn render(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= frame.image.x || id.y >= frame.image.y {
        return;
    }
    let ray = camera_ray(f32(id.x) + 0.5, f32(id.y) + 0.5);
    let hit = trace(ray);
    var rgba = vec4<f32>(0.0);
    if hit.hit {
        // Stored as unorm: the byte b comes back as round(b / 255 · 255) = b.
        rgba = vec4<f32>(shade(hit, ray.dir)) / 255.0;
    }
    textureStore(target_image, vec2<i32>(id.xy), rgba);
}
