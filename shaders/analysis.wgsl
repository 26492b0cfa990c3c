// The analysis (feedback) pass: `client/core/src/analysis.rs`, GPU twin. Appended to
// `traverse.wgsl`. One invocation per entry of the pixel list (`pixels`, each `x | y << 16`,
// the CPU twin's `pack_pixel`): it samples that full-resolution pixel through its centre,
// exactly like `analysis::sample_pixel`, and writes one `FeedbackSample` (16 bytes, `#[repr(C)]`
// twin in Rust) at the same index. Pixels outside the frame, and misses, get `MISS`.
// Invocations run in rows of `frame.image.w` (the dispatch is 2-D so long lists stay within
// the workgroup-count limit); `frame.image.z` is the list's length.

struct FeedbackSample {
    node: u32,
    subtreelet: u32,
    error: f32,
    t: f32,
}

@group(0) @binding(2) var<storage, read_write> feedback: array<FeedbackSample>;
@group(0) @binding(3) var<storage, read> pixels: array<u32>;

@compute @workgroup_size(64, 1, 1)
fn analysis(@builtin(global_invocation_id) id: vec3<u32>) {
    let index = id.y * frame.image.w + id.x;
    if id.x >= frame.image.w || index >= frame.image.z {
        return;
    }
    let packed = pixels[index];
    let px = packed & 0xFFFFu;
    let py = packed >> 16u;
    var out = FeedbackSample(NONE, NONE, 0.0, 0.0);
    if px < frame.image.x && py < frame.image.y {
        let hit = trace(camera_ray(f32(px) + 0.5, f32(py) + 0.5));
        if hit.hit {
            out = FeedbackSample(hit.node, hit.subtreelet, hit.error, hit.t * frame.lod.z);
        }
    }
    feedback[index] = out;
}
