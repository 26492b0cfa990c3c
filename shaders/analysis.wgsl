// The analysis (feedback) pass: `client/src/analysis.rs`, GPU twin. Appended to
// `traverse.wgsl`. One invocation per feedback element `(fx, fy)`: it samples the
// full-resolution pixel `(fx·n + ox, fy·n + oy)` through its centre, exactly like
// `analysis::sample_pixel`, and writes one `FeedbackSample` (16 bytes, `#[repr(C)]` twin in
// Rust). Elements whose pixel falls outside the frame, and misses, get `MISS`.

struct FeedbackSample {
    node: u32,
    subtreelet: u32,
    error: f32,
    t: f32,
}

@group(0) @binding(2) var<storage, read_write> feedback: array<FeedbackSample>;

@compute @workgroup_size(8, 8, 1)
fn analysis(@builtin(global_invocation_id) id: vec3<u32>) {
    let fw = frame.image.z;
    let fh = frame.image.w;
    if id.x >= fw || id.y >= fh {
        return;
    }
    let ratio = frame.sampling.x;
    let px = id.x * ratio + frame.sampling.y;
    let py = id.y * ratio + frame.sampling.z;
    var out = FeedbackSample(NONE, NONE, 0.0, 0.0);
    if px < frame.image.x && py < frame.image.y {
        let hit = trace(camera_ray(f32(px) + 0.5, f32(py) + 0.5));
        if hit.hit {
            out = FeedbackSample(hit.node, hit.subtreelet, hit.error, hit.t * frame.lod.z);
        }
    }
    feedback[id.y * fw + id.x] = out;
}
