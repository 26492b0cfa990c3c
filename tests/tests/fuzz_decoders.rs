//! Fuzzing on stable: a bounded, seeded mutation loop over the control-frame decoder (whole
//! frames through `check` + `parse`, and streams through `FrameDecoder` in pieces, as a server
//! and as a client) and over the treelet-message decoder (`parse_treelet_header`,
//! `check_treelet_message`, `decode_treelet_message`).
//!
//! Seeds are real frames and messages: a real scan (bunny) built into a real pool, its
//! `SceneInfo` (with and without the trained dictionary), `Hello`, request lists and deep
//! request lists over its treelet ids with a real camera's view, `Error`, `Goodbye`, and its
//! treelet messages exactly as the service sends them. Mutations know the formats: length
//! fields set to boundary values, the frame type byte swept, channel tables and block lengths
//! rewritten, non-finite floats, truncation, extension, duplication and splicing of frames.
//!
//! For every input: no panic (caught and counted — the count must be 0); a decoded frame
//! re-encodes to bytes that decode to the same frame; a streaming decoder never buffers more
//! than its capacity and never stalls; and no decoder allocates beyond what the bytes present
//! justify — the peak of live heap bytes during one decode, measured by a counting global
//! allocator in this test binary, stays within `ALLOC_SLACK + ALLOC_PER_BYTE × input length`
//! (plus the streaming decoder's fixed capacity). Lengths claimed but not present never turn
//! into allocations — except inside a `SceneInfo`, whose description bincode decodes under its
//! own limit ([`MAX_SCENE_DESCRIPTION_BYTES`]): there the bound is that limit.
//!
//! The quick test runs in CI; the 10-million-input run is ignored:
//! `cargo test --release -p arbor-tests --test fuzz_decoders -- --ignored --nocapture`.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::panic::{AssertUnwindSafe, catch_unwind};

use arbor_proto::TreeletId;
use arbor_proto::frame::{
    self, FrameDecoder, check_treelet_message, decode_treelet_message, encode, parse,
    parse_treelet_header,
};
use arbor_proto::limits::MAX_SCENE_DESCRIPTION_BYTES;
use arbor_proto::rng::SplitMix64;
use arbor_proto::wire::{ErrorCode, Frame, FrameType, HELLO_FLAGS, PROTOCOL_VERSION, ViewHint};
use arbor_server::octree::{BuildOptions, DepthChoice};
use arbor_server::service::treelets::ServedScene;
use arbor_tests::support::build_file;

// ---------------------------------------------------------------------------------------------
// Counting allocator: live heap bytes of the current thread and their peak.

struct Counting;

thread_local! {
    static LIVE: Cell<isize> = const { Cell::new(0) };
    static PEAK: Cell<isize> = const { Cell::new(0) };
}

fn account(delta: isize) {
    let _ = LIVE.try_with(|live| {
        let now = live.get() + delta;
        live.set(now);
        let _ = PEAK.try_with(|peak| peak.set(peak.get().max(now)));
    });
}

// SAFETY: every call is forwarded to the system allocator unchanged; the counters are
// thread-local cells without destructors.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        account(layout.size() as isize);
        // SAFETY: forwarded with the caller's layout.
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        account(-(layout.size() as isize));
        // SAFETY: forwarded with the caller's pointer and layout.
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        account(layout.size() as isize);
        // SAFETY: forwarded with the caller's layout.
        unsafe { System.alloc_zeroed(layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        account(new_size as isize - layout.size() as isize);
        // SAFETY: forwarded with the caller's pointer, layout and size.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// Runs `f` and returns its result with the peak of live heap bytes above the start.
fn peak_during<T>(f: impl FnOnce() -> T) -> (T, usize) {
    let base = LIVE.with(Cell::get);
    PEAK.with(|p| p.set(base));
    let out = f();
    let peak = PEAK.with(Cell::get) - base;
    (out, peak.max(0) as usize)
}

/// Fixed allocations a decode may make whatever its input (error messages, small tables).
const ALLOC_SLACK: usize = 64 << 10;
/// Heap bytes a decode may hold per input byte (decoded items are at most this much larger
/// than their encoding).
const ALLOC_PER_BYTE: usize = 4;

// ---------------------------------------------------------------------------------------------
// Seeds.

struct Seeds {
    frames: Vec<Vec<u8>>,
    messages: Vec<Vec<u8>>,
}

fn seeds() -> Seeds {
    let mut frames = Vec::new();
    let mut messages = Vec::new();
    for dictionary in [false, true] {
        let built = build_file(
            "meshes/stanford-bunny.obj",
            "bunny",
            &BuildOptions {
                depth: DepthChoice::Fixed(6),
                treelet_bytes: 1024,
                dictionary,
                progress: false,
                ..BuildOptions::default()
            },
        );
        let description = built.scene.description.clone();
        let channels = description.layout.channels().to_vec();
        let count = description.treelet_count;
        frames.push(
            encode(&Frame::SceneInfo {
                description: Box::new(description),
            })
            .unwrap(),
        );
        if dictionary {
            continue;
        }
        let served = ServedScene::new(built.scene);
        for id in (0..count).step_by((count as usize / 24).max(1)) {
            messages.push(served.message(TreeletId(id), &channels).unwrap().to_vec());
        }
        let ids: Vec<TreeletId> = (0..count.min(300)).map(TreeletId).collect();
        let view = ViewHint {
            eye: [0.5, -1.5, 0.25],
            forward: [0.0, 1.0, 0.0],
            up: [0.0, 0.0, 1.0],
            tan_half_fov_y: 0.5,
            aspect: 1.0,
            footprint: 1.0 / 512.0,
            free_slots: 64,
        };
        frames.push(
            encode(&Frame::Hello {
                version: PROTOCOL_VERSION,
                scene: "bunny".into(),
                channels: channels.clone(),
                token: "bunny-token".into(),
                flags: HELLO_FLAGS,
                view: Some(view),
            })
            .unwrap(),
        );
        for len in [1, 7, 64, 300] {
            let items: Vec<(TreeletId, f32)> = ids[..len.min(ids.len())]
                .iter()
                .map(|&t| (t, 1000.0 / (1.0 + t.0 as f32)))
                .collect();
            frames.push(
                encode(&Frame::RequestList {
                    seq: len as u64,
                    items: items.clone(),
                })
                .unwrap(),
            );
            frames.push(
                encode(&Frame::DeepRequestList {
                    seq: len as u64 + 1,
                    view: ViewHint {
                        free_slots: 400,
                        ..view
                    },
                    items: items.iter().map(|&(t, p)| (t, p, 2.5)).collect(),
                    prefetch_from: items.len() as u32 / 2,
                })
                .unwrap(),
            );
            // The compact form, ids in serving order (jumps up and down: varints of 1–5 bytes).
            frames.push(
                encode(&Frame::RankedRequestList {
                    seq: len as u64 + 2,
                    view,
                    items: items
                        .iter()
                        .rev()
                        .enumerate()
                        .map(|(i, &(t, _))| (t, (i as i16 - 3).wrapping_mul(4099)))
                        .chain([(TreeletId(u32::MAX - 1), 0), (TreeletId(0), -1)])
                        .collect(),
                    prefetch_from: items.len() as u32 / 3,
                })
                .unwrap(),
            );
        }
        frames.push(
            encode(&Frame::Error {
                code: ErrorCode::Unauthorized,
                message: "wrong token for scene bunny".into(),
            })
            .unwrap(),
        );
        frames.push(
            encode(&Frame::Goodbye {
                code: ErrorCode::ShuttingDown,
            })
            .unwrap(),
        );
    }
    Seeds { frames, messages }
}

// ---------------------------------------------------------------------------------------------
// Structure-aware mutations.

const INTERESTING_U32: [u32; 14] = [
    0,
    1,
    2,
    4,
    5,
    0x7f,
    0x80,
    0xffff,
    0x1_0000,
    (1 << 20) - 1,
    1 << 20,
    (1 << 20) + 1,
    0x7fff_ffff,
    u32::MAX,
];

fn write_u32(buf: &mut [u8], at: usize, v: u32) {
    if at + 4 <= buf.len() {
        buf[at..at + 4].copy_from_slice(&v.to_le_bytes());
    }
}

/// One mutation of `buf` (a frame or a message); `other` may be spliced in.
fn mutate(rng: &mut SplitMix64, buf: &mut Vec<u8>, other: &[u8], is_frame: bool) {
    let pick = |rng: &mut SplitMix64, n: usize| rng.below(n.max(1) as u64) as usize;
    match rng.below(12) {
        0 if !buf.is_empty() => {
            let i = pick(rng, buf.len());
            buf[i] ^= 1 << rng.below(8);
        }
        1 if !buf.is_empty() => {
            let i = pick(rng, buf.len());
            buf[i] = [0, 1, 0x7f, 0x80, 0xfe, 0xff][pick(rng, 6)];
        }
        2 => {
            let at = pick(rng, buf.len());
            write_u32(buf, at, INTERESTING_U32[pick(rng, INTERESTING_U32.len())]);
        }
        3 => {
            // The length field that opens a frame, or the treelet id / node block length of a
            // message: around the real value and at the limits.
            let real = buf.len().saturating_sub(5) as u32;
            let v = [real, real + 1, real.wrapping_sub(1), real * 2, 0, u32::MAX][pick(rng, 6)];
            let at = if is_frame || rng.below(2) == 0 {
                0
            } else {
                buf.len()
                    .saturating_sub(4)
                    .min(7 + 5 * usize::from(buf.get(6).copied().unwrap_or(0)))
            };
            write_u32(buf, at, v);
        }
        4 if buf.len() > 6 => {
            if is_frame {
                buf[4] = rng.below(9) as u8;
            } else {
                // Channel count, then a channel id of the table.
                buf[6] = rng.below(10) as u8;
                let i = 7 + 5 * pick(rng, 8);
                if i < buf.len() {
                    buf[i] = rng.below(6) as u8;
                }
            }
        }
        5 => {
            let keep = pick(rng, buf.len() + 1);
            buf.truncate(keep);
        }
        6 => {
            let at = pick(rng, buf.len() + 1);
            let n = 1 + pick(rng, 16);
            let bytes: Vec<u8> = (0..n).map(|_| rng.next_u64() as u8).collect();
            buf.splice(at..at, bytes);
        }
        7 if !buf.is_empty() => {
            let a = pick(rng, buf.len());
            let b = (a + 1 + pick(rng, 64)).min(buf.len());
            let copy = buf[a..b].to_vec();
            let at = pick(rng, buf.len() + 1);
            buf.splice(at..at, copy);
        }
        8 => buf.extend_from_slice(other),
        9 if buf.len() >= 4 => {
            // A non-finite float where priorities, errors and the view live.
            let at = pick(rng, buf.len() - 3);
            let v = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY, -0.0, f32::MAX][pick(rng, 5)];
            buf[at..at + 4].copy_from_slice(&v.to_le_bytes());
        }
        10 if buf.len() >= 2 => {
            let at = pick(rng, buf.len() - 1);
            let v = [0u16, 1, 0x7fff, 0xffff, 513][pick(rng, 5)];
            buf[at..at + 2].copy_from_slice(&v.to_le_bytes());
        }
        _ => {
            let at = pick(rng, buf.len());
            let n = pick(rng, buf.len() - at + 1);
            buf.drain(at..at + n);
        }
    }
}

fn input(rng: &mut SplitMix64, seeds: &[Vec<u8>], is_frame: bool) -> Vec<u8> {
    // The SceneInfo with a dictionary is large: pick it rarely, the rest evenly.
    let mut buf = seeds[rng.below(seeds.len() as u64) as usize].clone();
    if buf.len() > 8192 && rng.below(64) != 0 {
        buf = seeds[0].clone();
    }
    let other = &seeds[rng.below(seeds.len() as u64) as usize];
    let other = if other.len() > 8192 {
        &seeds[0][..]
    } else {
        other
    };
    for _ in 0..1 + rng.below(4) {
        mutate(rng, &mut buf, other, is_frame);
    }
    buf
}

// ---------------------------------------------------------------------------------------------
// The checks.

/// What a run found.
#[derive(Debug, Default)]
struct Figures {
    inputs: u64,
    accepted: u64,
    panics: u64,
    peak_alloc: usize,
}

fn check_alloc(what: &str, input: &[u8], peak: usize, fixed: usize) {
    let bound = fixed + ALLOC_SLACK + ALLOC_PER_BYTE * input.len();
    assert!(
        peak <= bound,
        "{what}: {peak} heap bytes for {} input bytes (bound {bound}); input {:02x?}",
        input.len(),
        &input[..input.len().min(64)]
    );
}

/// One input through `check` + `parse` and through streaming decoders of both sides.
fn frame_case(rng: &mut SplitMix64, buf: &[u8]) -> bool {
    let (accepted, peak) = peak_during(|| match frame::check(buf) {
        Ok(Some(len)) => match parse(&buf[..len]) {
            Ok(f) => {
                // Compared as bytes: a mutated float may be NaN, which no frame equals.
                let again = encode(&f).expect("a decoded frame re-encodes");
                let twice = encode(&parse(&again).expect("and decodes again")).unwrap();
                assert_eq!(twice, again);
                true
            }
            Err(_) => false,
        },
        _ => false,
    });
    // A scene description is decoded by bincode, whose limit bounds what lengths it believes:
    // a short SceneInfo may make a client allocate up to that limit, never more.
    let description_limit = if buf.get(4) == Some(&(FrameType::SceneInfo as u8)) {
        MAX_SCENE_DESCRIPTION_BYTES
    } else {
        0
    };
    check_alloc("check + parse", buf, peak, description_limit);
    for mut decoder in [FrameDecoder::for_server(), FrameDecoder::for_client()] {
        let piece = 1 + rng.below(200) as usize;
        let capacity = decoder.capacity();
        let ((), peak) = peak_during(|| stream(&mut decoder, buf, piece));
        // The decoder's buffer grows with the bytes pushed, never past its capacity; any of
        // the frames in a stream may be a SceneInfo.
        let fixed = buf.len().min(capacity) + MAX_SCENE_DESCRIPTION_BYTES;
        check_alloc("FrameDecoder", buf, peak, fixed);
    }
    accepted
}

fn stream(decoder: &mut FrameDecoder, buf: &[u8], piece: usize) {
    'feed: for chunk in buf.chunks(piece) {
        let mut chunk = chunk;
        while !chunk.is_empty() {
            let taken = decoder.push(chunk);
            assert!(decoder.buffered() <= decoder.capacity());
            chunk = &chunk[taken..];
            let mut progressed = taken > 0;
            loop {
                match decoder.next() {
                    Ok(Some(_)) => progressed = true,
                    Ok(None) => break,
                    Err(_) => break 'feed,
                }
            }
            assert!(
                progressed,
                "decoder stalled with {} buffered",
                decoder.buffered()
            );
        }
    }
}

/// One input through the treelet-message decoders.
fn message_case(buf: &[u8]) -> bool {
    let (accepted, peak) = peak_during(|| {
        let header = parse_treelet_header(buf);
        let checked = check_treelet_message(buf);
        match decode_treelet_message(buf) {
            Ok(m) => {
                let total = checked
                    .expect("decodable means checkable")
                    .expect("complete");
                assert_eq!(total, buf.len());
                let h = header.unwrap().unwrap();
                assert_eq!((h.id, h.used_nodes), (m.id, m.used_nodes));
                let blocks = m.nodes.len() + m.channels.iter().map(|c| c.1.len()).sum::<usize>();
                assert_eq!(blocks + h.header_len, buf.len());
                true
            }
            Err(_) => false,
        }
    });
    check_alloc("treelet message", buf, peak, 0);
    accepted
}

fn run(
    seeds: &[Vec<u8>],
    inputs: u64,
    seed: u64,
    is_frame: bool,
    case: impl Fn(&mut SplitMix64, &[u8]) -> bool,
) -> Figures {
    let mut rng = SplitMix64::new(seed);
    let mut f = Figures::default();
    // Seeds themselves first: they must decode.
    for s in seeds {
        assert!(case(&mut rng, s), "a real seed was refused");
    }
    let quiet = std::panic::take_hook();
    std::panic::set_hook(Box::new(|_| {}));
    for _ in 0..inputs {
        let buf = input(&mut rng, seeds, is_frame);
        let base = LIVE.with(Cell::get);
        PEAK.with(|p| p.set(base));
        match catch_unwind(AssertUnwindSafe(|| case(&mut rng, &buf))) {
            Ok(accepted) => f.accepted += u64::from(accepted),
            Err(_) => {
                std::panic::set_hook(quiet);
                // Run it again with the hook in place, so the panic is reported.
                case(&mut rng, &buf);
                panic!("unreachable: the input panicked once");
            }
        }
        f.peak_alloc = f
            .peak_alloc
            .max((PEAK.with(Cell::get) - base).max(0) as usize);
        f.inputs += 1;
    }
    let _ = std::panic::take_hook();
    std::panic::set_hook(quiet);
    f
}

fn fuzz(inputs: u64) {
    let seeds = seeds();
    let started = std::time::Instant::now();
    let frames = run(&seeds.frames, inputs, 0x5eed_f4a3e, true, frame_case);
    let frame_s = started.elapsed().as_secs_f64();
    let started = std::time::Instant::now();
    let messages = run(&seeds.messages, inputs, 0x5eed_7ee1, false, |_, b| {
        message_case(b)
    });
    let message_s = started.elapsed().as_secs_f64();
    eprintln!(
        "frame decoder: {} inputs ({} seeds) in {frame_s:.1} s, {} decoded, {} panics, peak heap \
         per input {} B; treelet-message decoder: {} inputs ({} seeds) in {message_s:.1} s, {} \
         decoded, {} panics, peak heap per input {} B",
        frames.inputs,
        seeds.frames.len(),
        frames.accepted,
        frames.panics,
        frames.peak_alloc,
        messages.inputs,
        seeds.messages.len(),
        messages.accepted,
        messages.panics,
        messages.peak_alloc,
    );
    assert_eq!(frames.panics + messages.panics, 0);
    // The mutations must reach past the first checks: some inputs still decode.
    assert!(frames.accepted > 0 && frames.accepted < frames.inputs);
    assert!(messages.accepted > 0 && messages.accepted < messages.inputs);
}

#[test]
fn mutated_frames_and_messages_never_panic_nor_over_allocate() {
    fuzz(20_000);
}

#[test]
#[ignore = "10 million inputs per decoder: run with --release -- --ignored"]
fn ten_million_inputs_per_decoder() {
    fuzz(10_000_000);
}
