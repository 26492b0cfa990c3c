//! CPU phases of one client cycle, on a real scan: the analysis twin (128×128 feedback of a
//! 1024² frame), presort (both priority policies, 1,000+ distinct requests), the slot update
//! (ageing, visibility, 256 insertions into a full buffer with evictions) and the upload range
//! merge (fill ratio 0, 0.6 and 1), the CPU render of the full frame with the cost of its rays
//! (generated per ray from the camera against `PixelRays`, in one run), and decoding 256
//! received treelets with the scene's zstd dictionaries raw (loaded on every block) and prepared
//! once.
//!
//! `cargo bench -p arbor-tests --bench cycle` (release). Prints a table; no assertion on time.

use std::time::{Duration, Instant};

use arbor_client_core::analysis::{AnalysisConfig, Feedback, analyse};
use arbor_client_core::camera::CameraPath;
use arbor_client_core::incore::SceneFrame;
use arbor_client_core::presort::{Presort, PriorityPolicy};
use arbor_client_core::render::{Light, render};
use arbor_client_core::slots::{DecodedTreelet, InsertOutcome, SlotBuffer, SlotConfig};
use arbor_client_core::traverse::Ray;
use arbor_client_core::upload::merge_ranges;
use arbor_proto::codec::PreparedDictionaries;
use arbor_server::octree::BuildOptions;
use arbor_tests::support::{build_file, decoded_treelets};

const FRAME: u32 = 1024;
const RATIO: u32 = 8;
const REPS: u32 = 20;

fn best<T>(reps: u32, mut f: impl FnMut() -> T) -> (Duration, T) {
    let mut best = Duration::MAX;
    let mut last = None;
    for _ in 0..reps {
        let t = Instant::now();
        let out = f();
        best = best.min(t.elapsed());
        last = Some(out);
    }
    (best, last.unwrap())
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

fn main() {
    let built = build_file(
        "points/lion_takanawa.copc.laz",
        "lion",
        &BuildOptions {
            treelet_bytes: 1024,
            ..BuildOptions::default()
        },
    );
    let d = built.scene.description.clone();
    let channels = d.layout.channels().to_vec();
    let treelets: Vec<DecodedTreelet> = decoded_treelets(&built.scene);
    let frame = SceneFrame::of(&d);
    let camera = CameraPath::Static.camera(0, &frame, 7, FRAME, FRAME);
    let config = AnalysisConfig {
        ratio: RATIO,
        lod_bias: 1.0,
    };
    println!(
        "lion, 1 KiB treelets ({} treelets, depth {}), frame {FRAME}², feedback {}², best of {REPS}",
        d.treelet_count,
        d.max_depth,
        FRAME / RATIO
    );

    // Grow the resident set level by level until the view asks for 1,000+ treelets.
    let slot_bytes = SlotBuffer::slot_bytes(d.treelet_nodes, &channels);
    let capacity = d.treelet_count / 2;
    let new_buffer = || {
        SlotBuffer::new(
            SlotConfig {
                budget_bytes: u64::from(capacity) * slot_bytes,
                treelet_nodes: d.treelet_nodes,
                channels: channels.clone(),
                visibility_max: (RATIO * RATIO) as u16,
                load_limit: u32::MAX,
            },
            treelets[0].clone(),
        )
        .unwrap()
    };
    let mut slots = new_buffer();
    let mut feedback = Feedback::default();
    let mut presort = Presort::new(PriorityPolicy::ErrorTimesPixels, 65_536);
    let mut depth = 0;
    let mut requests;
    loop {
        analyse(&slots.view(), &frame, &camera, &config, 0, &mut feedback);
        let all: Vec<_> = (0..u64::from(RATIO * RATIO))
            .flat_map(|c| {
                let mut f = Feedback::default();
                analyse(&slots.view(), &frame, &camera, &config, c, &mut f);
                f.samples
            })
            .collect();
        requests = presort
            .run(
                &all,
                d.treelet_nodes,
                slots.capacity(),
                |s| slots.parent_slot(s),
                |_| false,
            )
            .distinct_requests;
        if requests >= 1000 || depth > d.max_depth {
            break;
        }
        depth += 1;
        for t in treelets
            .iter()
            .filter(|t| t.treelet.header.root_depth == depth)
        {
            slots.insert(t.clone());
        }
    }
    println!(
        "resident: treelets with root depth ≤ {depth}: {} slots of {}; one full jitter round asks \
         for {requests} distinct treelets",
        slots.used_slots(),
        slots.capacity()
    );

    let (t_analysis, _) = best(REPS, || {
        analyse(&slots.view(), &frame, &camera, &config, 5, &mut feedback);
    });
    let hits = feedback.samples.iter().filter(|s| s.is_hit()).count();
    // Presort over a whole round of samples so the list has 1,000+ entries, then per cycle.
    let round: Vec<_> = (0..u64::from(RATIO * RATIO))
        .flat_map(|c| {
            let mut f = Feedback::default();
            analyse(&slots.view(), &frame, &camera, &config, c, &mut f);
            f.samples
        })
        .collect();
    println!("\n{:<44} {:>10}", "phase", "ms");
    println!(
        "{:<44} {:>10.3}",
        format!("analysis twin ({}² samples, {hits} hits)", FRAME / RATIO),
        ms(t_analysis)
    );
    // The CPU render of the full frame, and what generating its rays costs: per ray from the
    // camera (the tangent, aspect and right vector each time) against `PixelRays` (once).
    let (t_render, image) = best(REPS, || {
        render(&slots.view(), &frame, &camera, 1.0, &Light::default())
    });
    let pixels = FRAME * FRAME;
    let ray_sum = |ray: &dyn Fn(f64, f64) -> Ray| {
        (0..pixels)
            .map(|i| {
                ray(f64::from(i % FRAME) + 0.5, f64::from(i / FRAME) + 0.5)
                    .dir
                    .x
            })
            .sum::<f64>()
    };
    let (t_per_ray, a) = best(REPS, || ray_sum(&|x, y| camera.ray(x, y)));
    let rays = camera.pixel_rays();
    let (t_shared, b) = best(REPS, || ray_sum(&|x, y| rays.ray(x, y)));
    assert_eq!(a.to_bits(), b.to_bits(), "the same rays either way");
    println!(
        "{:<44} {:>10.3}",
        format!("CPU render ({FRAME}², {} px covered)", image.coverage()),
        ms(t_render)
    );
    println!(
        "{:<44} {:>10.3}",
        format!("{FRAME}² rays, one thread: Camera::ray each"),
        ms(t_per_ray)
    );
    println!(
        "{:<44} {:>10.3}",
        format!("{FRAME}² rays, one thread: PixelRays"),
        ms(t_shared)
    );
    for policy in [PriorityPolicy::MaxError, PriorityPolicy::ErrorTimesPixels] {
        let mut p = Presort::new(policy, 65_536);
        let (t, out) = best(REPS, || {
            p.run(
                &feedback.samples,
                d.treelet_nodes,
                slots.capacity(),
                |s| slots.parent_slot(s),
                |_| false,
            )
        });
        let (t_round, out_round) = best(REPS, || {
            p.run(
                &round,
                d.treelet_nodes,
                slots.capacity(),
                |s| slots.parent_slot(s),
                |_| false,
            )
        });
        println!(
            "{:<44} {:>10.3}",
            format!(
                "presort {} (1 cycle, {} requests)",
                policy.name(),
                out.requests.len()
            ),
            ms(t)
        );
        println!(
            "{:<44} {:>10.3}",
            format!(
                "presort {} ({} samples, {} requests)",
                policy.name(),
                round.len(),
                out_round.requests.len()
            ),
            ms(t_round)
        );
    }

    // Slot update: fill a small buffer, then insert 256 more (each needing an eviction).
    let small_capacity = 2048.min(d.treelet_count / 2);
    let small = || {
        let mut s = SlotBuffer::new(
            SlotConfig {
                budget_bytes: u64::from(small_capacity) * slot_bytes,
                treelet_nodes: d.treelet_nodes,
                channels: channels.clone(),
                visibility_max: (RATIO * RATIO) as u16,
                load_limit: u32::MAX,
            },
            treelets[0].clone(),
        )
        .unwrap();
        let mut next = 1;
        while s.used_slots() < s.capacity() && next < treelets.len() {
            s.insert(treelets[next].clone());
            next += 1;
        }
        for _ in 0..=RATIO * RATIO {
            s.begin_cycle();
        }
        let _ = s.take_dirty();
        (s, next)
    };
    let mut t_update = Duration::MAX;
    let mut t_merge = [Duration::MAX; 3];
    let mut ranges = [0usize; 3];
    let mut stats = (0u32, 0u32, 0usize);
    for _ in 0..5 {
        let (mut s, next) = small();
        let batch: Vec<_> = treelets[next..].iter().take(4096).cloned().collect();
        let visible: Vec<u32> = (0..s.capacity()).step_by(7).collect();
        let t = Instant::now();
        s.begin_cycle();
        for &v in &visible {
            s.mark_visible(v);
        }
        let mut inserted = 0u32;
        let mut evicted = 0u32;
        for t in batch {
            if inserted == 256 {
                break;
            }
            if let InsertOutcome::Inserted { evicted: e, .. } = s.insert(t) {
                inserted += 1;
                evicted += e;
            }
        }
        let dirty = s.take_dirty();
        t_update = t_update.min(t.elapsed());
        stats = (inserted, evicted, dirty.len());
        for (k, fill) in [0.0f32, 0.6, 1.0].into_iter().enumerate() {
            let t = Instant::now();
            let r = merge_ranges(&dirty, fill);
            t_merge[k] = t_merge[k].min(t.elapsed());
            ranges[k] = r.len();
        }
    }
    println!(
        "{:<44} {:>10.3}",
        format!(
            "slot update ({} inserted, {} evicted, {} slots)",
            stats.0, stats.1, small_capacity
        ),
        ms(t_update)
    );
    for (k, fill) in [0.0f32, 0.6, 1.0].into_iter().enumerate() {
        println!(
            "{:<44} {:>10.4}",
            format!(
                "range merge fill {fill} ({} dirty → {} ranges)",
                stats.2, ranges[k]
            ),
            ms(t_merge[k])
        );
    }
    // Decoding what a cycle receives: 256 treelets as messages, with the scene's dictionaries
    // loaded on every block (what `codec::decompress` does with a raw dictionary) and prepared
    // once (what the session does).
    let messages: Vec<_> = (0..256.min(d.treelet_count))
        .map(|i| {
            let id = arbor_proto::TreeletId(i);
            let nodes = built.scene.nodes(id).unwrap().unwrap().to_vec();
            let attrs: Vec<_> = channels
                .iter()
                .map(|&c| (c, built.scene.channel(c, id).unwrap().unwrap().to_vec()))
                .collect();
            (id, nodes, attrs)
        })
        .collect();
    let prepared = PreparedDictionaries::of(&d);
    let decode_all = |prepared: Option<&PreparedDictionaries>| {
        for (id, nodes, attrs) in &messages {
            let refs: Vec<_> = attrs.iter().map(|(c, b)| (*c, &b[..])).collect();
            let t = match prepared {
                Some(p) => {
                    DecodedTreelet::from_blocks_prepared(*id, nodes, &refs, &d, p, &channels)
                }
                None => DecodedTreelet::from_blocks(*id, nodes, &refs, &d, &channels),
            };
            std::hint::black_box(t.unwrap());
        }
    };
    let (raw, ()) = best(REPS, || decode_all(None));
    let (fast, ()) = best(REPS, || decode_all(Some(&prepared)));
    for (what, t) in [("raw dictionaries", raw), ("prepared dictionaries", fast)] {
        println!(
            "{:<44} {:>10.3}",
            format!("decode {} treelets, {what}", messages.len()),
            ms(t)
        );
    }
}
