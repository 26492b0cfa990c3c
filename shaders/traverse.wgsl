// The GPU twin of `client/src/trace.rs`: one ray in, the nearest voxel it stops at out.
//
// Both passes are this file followed by the pass file (`analysis.wgsl`, `render.wgsl`); the
// build script validates each concatenation with naga. Every step below carries the number
// of the step in the module docs of `trace.rs`, and the names are the same, so the two can be
// read side by side. The only intended differences are the number format and the units.
//
// # Units and precision (f32 here, f64 on the CPU)
//
// Coordinates are camera-relative like on the CPU, but measured in *units* of
// `edge / 2^31`, the edge of a voxel at depth 31 (the deepest the format allows). A face of
// the box of cell `c` at depth `d` lies at the integer `F = c << (31 − d)` units from the
// root's minimum corner, for every depth: a face shared by two voxels, or by a voxel and its
// parent, has one integer `F`. The camera is given as a 64-bit integer `C` (split into a
// signed high and an unsigned low word) plus a fraction `f` in `[0, 1)` units, computed on the
// CPU in f64. A face's camera-relative coordinate is `face(F) = f32(F − C) − f`, with the
// 64-bit difference taken exactly in integers and rounded to f32 once (twice beyond 2^32
// units, where only the relative precision matters). So:
//
// - one face has one f32 value at every depth, like the CPU's one f64 value: a child's entry
//   is never before its parent's, neighbours meet exactly;
// - a face near the camera is represented to the full 24-bit mantissa *of its distance to the
//   camera*, whatever the depth (down to depth 31) and however large the world coordinates
//   are: the large parts cancel in integers, not in floats. Deep levels stay as precise as
//   shallow ones; there is no incremental accumulation of rounding errors.
//
// What remains f32: the ray direction (computed from the camera basis in f32), the divisions
// of the slab test and the keys `t` (relative error a few 2^-24), and the camera fraction
// (2^-24 units). Rays that the CPU twin finds tied between two voxels within those errors
// (rays through voxel edges and corners, grazing silhouettes) may pick the other voxel here;
// the tests measure how often. Limits: the camera must lie within 2^61 units (2^30 root
// edges) of the root, else the frame is marked invalid and every ray misses; the pixel angle
// (times the LOD bias) must stay well above 2^-24 rad ≈ 6e-8 — below it neither an f32 ray
// direction nor a face coordinate at the distance where such a pixel still spans a voxel
// resolves the pixel (a whole scene framed from 10^6 edges away; `gpu_twin` measures it);
// `t` is output in world units as `t_units · (edge / 2^31)`, exact up to one rounding.
//
// Sizes in units are exact powers of two (`2^(31 − d)`), so the LOD test
// `size ≤ t · pixel_angle · lod_bias` and the screen error
// `log2(size) − log2(t) − log2(pixel_angle) − log2(lod_bias)` need no world lengths at all:
// the unit cancels.

const MAX_STEPS: u32 = 65536u;
const MAX_DEPTH: u32 = 31u;
const NONE: u32 = 0xffffffffu;
const MAX_SCREEN_ERROR: f32 = 64.0;
// log2 of f64::MIN_POSITIVE: what `trace::safe_log2` gives a zero or negative argument.
const LOG2_TINY: f32 = -1022.0;
// Stands for ±∞ (WGSL has no infinity literal); no key comes near it.
const BIG: f32 = 3.0e38;
// 2^32 as f32, to assemble a 64-bit magnitude.
const TWO_32: f32 = 4294967296.0;

// Bits of `FrameUniform.flags.x`.
const FLAG_VALID: u32 = 1u;
const FLAG_PROJECT: u32 = 2u;
const FLAG_COLOR: u32 = 4u;
const FLAG_NORMAL: u32 = 8u;
const FLAG_DENSITY: u32 = 16u;

// One node record: `arbor_proto::Node` as two words.
struct Node {
    first_child: u32,
    // valid_mask | leaf_mask << 8 | spare << 16
    masks: u32,
}

// Everything fixed for one pass; `client/src/gpu/layout.rs` has the Rust twin and the docs of
// every member.
struct FrameUniform {
    cam_hi: vec4<i32>,
    cam_lo: vec4<u32>,
    cam_frac: vec4<f32>,
    forward: vec4<f32>,
    right: vec4<f32>,
    up: vec4<f32>,
    light: vec4<f32>,
    screen: vec4<f32>,
    lod: vec4<f32>,
    image: vec4<u32>,
    sampling: vec4<u32>,
    flags: vec4<u32>,
}

@group(0) @binding(0) var<uniform> frame: FrameUniform;
@group(0) @binding(1) var<storage, read> nodes: array<Node>;

struct Ray {
    dir: vec3<f32>,
}

struct Slab {
    hit: bool,
    t_enter: f32,
    entry_axis: u32,
    entry_sign: f32,
}

struct Hit {
    hit: bool,
    node: u32,
    depth: u32,
    // In units (see the header); `frame.lod.z` converts to world lengths.
    t: f32,
    leaf: bool,
    subtreelet: u32,
    error: f32,
    entry_axis: u32,
    entry_sign: f32,
}

fn no_hit() -> Hit {
    return Hit(false, NONE, 0u, 0.0, false, NONE, 0.0, 0u, -1.0);
}

fn valid_mask(n: Node) -> u32 {
    return n.masks & 0xffu;
}

fn leaf_mask(n: Node) -> u32 {
    return (n.masks >> 8u) & 0xffu;
}

// The ray through continuous pixel coordinates `(px, py)`: `Camera::ray`.
fn camera_ray(px: f32, py: f32) -> Ray {
    // `(2·px/w − 1)·h·aspect` with the division folded into `screen.x` on the CPU: the
    // brackets are exact, so the centre row and column are exactly 0 on every device.
    let sx = (2.0 * px - frame.screen.z) * frame.screen.x;
    let sy = (frame.screen.w - 2.0 * py) * frame.screen.x;
    let d = frame.forward.xyz + frame.right.xyz * sx + frame.up.xyz * sy;
    let len = length(d);
    var dir = vec3<f32>(0.0);
    if len > 0.0 {
        dir = d / len;
    }
    return Ray(dir);
}

// Camera-relative coordinate, in units, of the face at integer `f` along axis `a` (header).
fn face(f: u32, a: u32) -> f32 {
    let c_lo = frame.cam_lo[a];
    let c_hi = frame.cam_hi[a];
    // D = F − C in 64-bit two's complement; F has a zero high word.
    let lo = f - c_lo;
    let borrow = select(0, 1, f < c_lo);
    let hi = -c_hi - borrow;
    var value: f32;
    if hi < 0 {
        // Negate to get the magnitude: two's complement of (hi, lo).
        let m_lo = 0u - lo;
        let m_hi = u32(~hi) + select(0u, 1u, lo == 0u);
        value = -(f32(m_hi) * TWO_32 + f32(m_lo));
    } else {
        value = f32(u32(hi)) * TWO_32 + f32(lo);
    }
    return value - frame.cam_frac[a];
}

// Step 2: slab test of the camera-relative box `[lo, hi]` along `dir`.
fn slab(lo: vec3<f32>, hi: vec3<f32>, dir: vec3<f32>) -> Slab {
    return slab_with(lo, hi, lo / dir, hi / dir, dir);
}

// `slab` with the face distances `t_lo = lo / dir`, `t_hi = hi / dir` given. Components where
// `dir` is 0 are not read. The traversal tests a node's children with `child_slabs`, from the
// same quotients (9 divided per node, not 6 per child), with the same results.
fn slab_with(lo: vec3<f32>, hi: vec3<f32>, t_lo: vec3<f32>, t_hi: vec3<f32>, dir: vec3<f32>) -> Slab {
    var t_enter = -BIG;
    var t_exit = BIG;
    var entry_axis = 0u;
    var entry_sign = -1.0;
    for (var a = 0u; a < 3u; a++) {
        let d = dir[a];
        if d == 0.0 {
            // Parallel: inside the closed slab or never in it.
            if !(lo[a] <= 0.0 && 0.0 <= hi[a]) {
                return Slab(false, 0.0, 0u, -1.0);
            }
            continue;
        }
        var near: f32;
        var far: f32;
        var sign: f32;
        if d > 0.0 {
            near = t_lo[a];
            far = t_hi[a];
            sign = -1.0;
        } else {
            near = t_hi[a];
            far = t_lo[a];
            sign = 1.0;
        }
        if near > t_enter {
            t_enter = near;
            entry_axis = a;
            entry_sign = sign;
        }
        if far < t_exit {
            t_exit = far;
        }
    }
    return Slab(t_enter <= t_exit && t_exit >= 0.0, t_enter, entry_axis, entry_sign);
}

// The slabs of one node's eight children, per axis: the ray's entry and exit in the low half
// (`near0`, `far0`) and the high half (`near1`, `far1`), from the node's low, middle and high
// faces and their distances — what `slab_with` derives per axis, ordered by the direction's
// sign once per node instead of once per child (as `ChildFaces` in traverse.rs). An axis the
// ray runs parallel to gives −BIG / BIG inside the closed half and BIG / −BIG outside it.
struct ChildSlabs {
    near0: vec3<f32>,
    far0: vec3<f32>,
    near1: vec3<f32>,
    far1: vec3<f32>,
}

fn child_slabs(
    lo: vec3<f32>,
    mid: vec3<f32>,
    hi: vec3<f32>,
    t_lo: vec3<f32>,
    t_mid: vec3<f32>,
    t_hi: vec3<f32>,
    dir: vec3<f32>,
) -> ChildSlabs {
    var s = ChildSlabs(vec3<f32>(0.0), vec3<f32>(0.0), vec3<f32>(0.0), vec3<f32>(0.0));
    for (var a = 0u; a < 3u; a++) {
        let d = dir[a];
        if d == 0.0 {
            let in0 = lo[a] <= 0.0 && 0.0 <= mid[a];
            let in1 = mid[a] <= 0.0 && 0.0 <= hi[a];
            s.near0[a] = select(BIG, -BIG, in0);
            s.far0[a] = select(-BIG, BIG, in0);
            s.near1[a] = select(BIG, -BIG, in1);
            s.far1[a] = select(-BIG, BIG, in1);
        } else if d > 0.0 {
            s.near0[a] = t_lo[a];
            s.far0[a] = t_mid[a];
            s.near1[a] = t_mid[a];
            s.far1[a] = t_hi[a];
        } else {
            s.near0[a] = t_mid[a];
            s.far0[a] = t_lo[a];
            s.near1[a] = t_hi[a];
            s.far1[a] = t_mid[a];
        }
    }
    return s;
}

// The entry of child `i` (`upper`: its half per axis), or BIG when the ray misses it: the
// largest of its three entries against the smallest of its three exits, as `slab_with` finds
// them.
fn child_enter(s: ChildSlabs, upper: vec3<bool>) -> f32 {
    let n = select(s.near0, s.near1, upper);
    let f = select(s.far0, s.far1, upper);
    let t_enter = max(n.x, max(n.y, n.z));
    let t_exit = min(f.x, min(f.y, f.z));
    if t_enter <= t_exit && t_exit >= 0.0 {
        return t_enter;
    }
    return BIG;
}

// The `Slab` of the picked child: its entry face is the first axis reaching the entry, as in
// `slab_with`.
fn child_slab(s: ChildSlabs, upper: vec3<bool>, t_enter: f32, dir: vec3<f32>) -> Slab {
    let n = select(s.near0, s.near1, upper);
    var e = -BIG;
    var entry_axis = 0u;
    var entry_sign = -1.0;
    for (var a = 0u; a < 3u; a++) {
        if dir[a] != 0.0 && n[a] > e {
            e = n[a];
            entry_axis = a;
            entry_sign = select(1.0, -1.0, dir[a] > 0.0);
        }
    }
    return Slab(true, t_enter, entry_axis, entry_sign);
}

// Edge of a voxel at `depth` (≤ 31), in units: exactly 2^(31 − depth).
fn size_units(depth: u32) -> f32 {
    return f32(1u << (MAX_DEPTH - depth));
}

// Whether a voxel of edge `size` hit at key `t` stops the descent by projection.
fn projects_small(size: f32, t: f32) -> bool {
    return (frame.flags.x & FLAG_PROJECT) != 0u && size <= t * frame.lod.x;
}

// `trace::screen_error` in units: log2(size) − log2(t) − log2(pixel_angle · lod_bias), the
// last term precomputed in f64 with the same guards (`frame.lod.y`).
fn screen_error(depth: u32, t: f32) -> f32 {
    var log_t = LOG2_TINY;
    if t > 0.0 {
        log_t = log2(t);
    }
    let e = f32(MAX_DEPTH - depth) - log_t - frame.lod.y;
    return clamp(e, -MAX_SCREEN_ERROR, MAX_SCREEN_ERROR);
}

fn make_hit(index: u32, node: Node, leaf: bool, depth: u32, s: Slab) -> Hit {
    let t = max(s.t_enter, 0.0);
    var subtreelet = NONE;
    if leaf {
        subtreelet = node.first_child;
    }
    return Hit(true, index, depth, t, leaf, subtreelet, screen_error(depth, t), s.entry_axis, s.entry_sign);
}

// Faces of cell `cell` at `depth` along every axis, as integers: low face and high face.
fn box_lo(cell: vec3<u32>, depth: u32) -> vec3<f32> {
    let s = MAX_DEPTH - depth;
    return vec3<f32>(face(cell.x << s, 0u), face(cell.y << s, 1u), face(cell.z << s, 2u));
}

fn box_hi(cell: vec3<u32>, depth: u32) -> vec3<f32> {
    let s = MAX_DEPTH - depth;
    let c = cell + vec3<u32>(1u);
    return vec3<f32>(face(c.x << s, 0u), face(c.y << s, 1u), face(c.z << s, 2u));
}

// `trace::trace`: steps 1–7 of its module docs.
fn trace(ray: Ray) -> Hit {
    // Step 1: the frame was checked on the CPU; a zero direction cannot hit.
    let count = arrayLength(&nodes);
    if (frame.flags.x & FLAG_VALID) == 0u || count == 0u || all(ray.dir == vec3<f32>(0.0)) {
        return no_hit();
    }
    let dir = ray.dir;
    let root = nodes[0];
    let max_depth = min(frame.sampling.w, MAX_DEPTH);

    // Steps 2–4 for the root.
    let root_slab = slab(box_lo(vec3<u32>(0u), 0u), box_hi(vec3<u32>(0u), 0u), dir);
    if !root_slab.hit {
        return no_hit();
    }
    let root_t = max(root_slab.t_enter, 0.0);
    let root_leaf = valid_mask(root) == 0u;
    if root_leaf || max_depth == 0u || projects_small(size_units(0u), root_t) {
        return make_hit(0u, root, root_leaf, 0u, root_slab);
    }

    // Step 5.
    var stack_node: array<u32, 32>;
    var stack_mask: array<u32, 32>;
    var stack_next: array<f32, 32>;
    stack_node[0] = 0u;
    stack_mask[0] = valid_mask(root);
    stack_next[0] = -BIG;
    var depth = 0u;
    var cell = vec3<u32>(0u);
    var best = no_hit();
    var best_t = BIG;

    // Step 6.
    for (var step = 0u; step < MAX_STEPS; step++) {
        let mask = stack_mask[depth];
        if mask == 0u || stack_next[depth] >= best_t {
            if depth == 0u {
                return best;
            }
            depth -= 1u;
            cell = cell >> vec3<u32>(1u);
            continue;
        }
        let parent_index = stack_node[depth];
        let parent = nodes[parent_index];
        let child_depth = depth + 1u;
        let size = size_units(child_depth);

        // The parent's low, middle and high faces per axis: every child face is one of them.
        let lo = box_lo(cell, depth);
        let hi = box_hi(cell, depth);
        let ms = MAX_DEPTH - child_depth;
        let mc = cell * 2u + vec3<u32>(1u);
        let mid = vec3<f32>(face(mc.x << ms, 0u), face(mc.y << ms, 1u), face(mc.z << ms, 2u));
        let t_lo = lo / dir;
        let t_mid = mid / dir;
        let t_hi = hi / dir;

        // Pick the nearest remaining child that is hit and could beat the best hit.
        let slabs = child_slabs(lo, mid, hi, t_lo, t_mid, t_hi, dir);
        var remaining = mask;
        var have_pick = false;
        var pick_i = 0u;
        var pick_enter = 0.0;
        var pick_t = BIG;
        var next = BIG;
        for (var i = 0u; i < 8u; i++) {
            if (mask & (1u << i)) == 0u {
                continue;
            }
            let bits = vec3<u32>((i >> 2u) & 1u, (i >> 1u) & 1u, i & 1u);
            let t_enter = child_enter(slabs, bits == vec3<u32>(1u));
            if t_enter == BIG {
                remaining &= ~(1u << i);
                continue;
            }
            let t = max(t_enter, 0.0);
            if t >= best_t {
                remaining &= ~(1u << i);
                continue;
            }
            if have_pick && t >= pick_t {
                next = min(next, t);
            } else {
                if have_pick {
                    next = min(next, pick_t);
                }
                have_pick = true;
                pick_i = i;
                pick_enter = t_enter;
                pick_t = t;
            }
        }
        if !have_pick {
            stack_mask[depth] = 0u;
            continue;
        }
        let i = pick_i;
        let t = pick_t;
        let pick_bits = vec3<u32>((i >> 2u) & 1u, (i >> 1u) & 1u, i & 1u);
        let pick_slab = child_slab(slabs, pick_bits == vec3<u32>(1u), pick_enter, dir);
        let child_cell = cell * 2u + pick_bits;
        stack_mask[depth] = remaining & ~(1u << i);
        stack_next[depth] = next;

        let rank = countOneBits(valid_mask(parent) & ((1u << i) - 1u));
        let child_index = parent_index + parent.first_child + rank;
        if child_index >= count {
            continue;
        }
        let child = nodes[child_index];
        let leaf = (leaf_mask(parent) & (1u << i)) != 0u;
        if leaf || child_depth >= max_depth || projects_small(size, t) {
            if t < best_t {
                best_t = t;
                best = make_hit(child_index, child, leaf, child_depth, pick_slab);
            }
            continue;
        }
        if valid_mask(child) == 0u {
            // An inner node without children: malformed, nothing to hit inside.
            continue;
        }
        depth += 1u;
        cell = child_cell;
        stack_node[depth] = child_index;
        stack_mask[depth] = valid_mask(child);
        stack_next[depth] = -BIG;
    }
    return best;
}
