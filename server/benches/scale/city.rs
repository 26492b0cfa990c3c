//! A city-sized tiled point set made from the real scans: the autzen airborne survey (110k
//! points over 1,177 × 562 ft) and the lion statue (342k photogrammetry points), copied into a
//! grid of LAZ tiles with offsets, jitter and per-tile variation, so a billion-point import can
//! be measured from data nobody here made up.
//!
//! A tile is 2,400 × 1,200 ft: four autzen copies (each turned 0° or 180°, raised by up to
//! ±15 ft, tinted), each densified `r` times with jitter (±1.25 ft across, ±0.2 ft up: denser
//! LiDAR of the same ground), and one lion scaled 15× standing on it, turned at random. Every
//! tile has its own LAS offset (its corner), scale 0.01 ft, point format 2 (xyz + RGB), LAZ.
//! Seeded: the same count gives the same files.

use std::path::{Path, PathBuf};

use arbor_proto::rng::SplitMix64;

/// Source points: position and 16-bit colour.
struct Scan {
    xyz: Vec<[f64; 3]>,
    rgb: Vec<[u16; 3]>,
    min: [f64; 3],
    max: [f64; 3],
}

fn read_scan(path: &Path) -> Scan {
    let mut reader = las::Reader::from_path(path).expect("reading a real scan");
    let pd = reader.read_all().expect("decoding a real scan");
    let xyz: Vec<[f64; 3]> = pd
        .x()
        .zip(pd.y())
        .zip(pd.z())
        .map(|((x, y), z)| [x, y, z])
        .collect();
    let rgb: Vec<[u16; 3]> = pd
        .rgb()
        .expect("the real scans have colour")
        .map(|(r, g, b)| [r, g, b])
        .collect();
    let mut min = [f64::INFINITY; 3];
    let mut max = [f64::NEG_INFINITY; 3];
    for p in &xyz {
        for a in 0..3 {
            min[a] = min[a].min(p[a]);
            max[a] = max[a].max(p[a]);
        }
    }
    Scan { xyz, rgb, min, max }
}

/// Tile footprint, feet.
pub const TILE: [f64; 2] = [2400.0, 1200.0];
/// Target points per tile.
pub const POINTS_PER_TILE: u64 = 2_000_000;

/// The tile files for `total` points under `dir` (made once, then reused).
pub fn city(data: &Path, dir: &Path, total: u64) -> Vec<PathBuf> {
    let marker = dir.join("complete");
    let tiles = total.div_ceil(POINTS_PER_TILE);
    let paths: Vec<PathBuf> = (0..tiles)
        .map(|i| dir.join(format!("tile_{i:05}.laz")))
        .collect();
    if marker.exists() {
        return paths;
    }
    std::fs::create_dir_all(dir).unwrap();
    let autzen = read_scan(&data.join("points/autzen_trim.las"));
    let lion = read_scan(&data.join("points/lion_takanawa.copc.laz"));
    let columns = (tiles as f64).sqrt().ceil() as u64;
    let mut left = total;
    for (i, path) in paths.iter().enumerate() {
        let n = left.min(POINTS_PER_TILE);
        left -= n;
        let corner = [
            636_000.0 + (i as u64 % columns) as f64 * TILE[0],
            848_000.0 + (i as u64 / columns) as f64 * TILE[1],
        ];
        write_tile(path, &autzen, &lion, corner, n, i as u64);
    }
    std::fs::write(&marker, total.to_string()).unwrap();
    paths
}

fn write_tile(path: &Path, autzen: &Scan, lion: &Scan, corner: [f64; 2], n: u64, seed: u64) {
    let mut rng = SplitMix64::new(0xC17E ^ seed.wrapping_mul(0x9E37_79B9));
    let mut builder = las::Builder::default();
    builder.version = las::Version::new(1, 2);
    builder.point_format = las::point::Format::new(2).unwrap();
    builder.point_format.is_compressed = true;
    let t = |offset: f64| las::Transform {
        scale: 0.01,
        offset,
    };
    builder.transforms = las::Vector {
        x: t(corner[0]),
        y: t(corner[1]),
        z: t(0.0),
    };
    let header = builder.into_header().unwrap();
    let mut w = las::Writer::from_path(path, header).unwrap();
    let mut written = 0u64;
    let put = |w: &mut las::Writer<_>, p: [f64; 3], c: [u16; 3]| {
        let point = las::Point {
            x: p[0],
            y: p[1],
            z: p[2],
            color: Some(las::Color::new(c[0], c[1], c[2])),
            ..Default::default()
        };
        w.write_point(point).unwrap();
    };
    // The lion first (15×, turned, standing on the ground at a random spot).
    let lion_points = (lion.xyz.len() as u64).min(n);
    let angle = rng.next_f64() * std::f64::consts::TAU;
    let (s, c) = angle.sin_cos();
    let at = [
        corner[0] + 200.0 + rng.next_f64() * (TILE[0] - 400.0),
        corner[1] + 200.0 + rng.next_f64() * (TILE[1] - 400.0),
        430.0,
    ];
    let lc = [0, 1].map(|a| (lion.min[a] + lion.max[a]) / 2.0);
    for k in 0..lion_points as usize {
        let q = lion.xyz[k];
        let (x, y) = ((q[0] - lc[0]) * 15.0, (q[1] - lc[1]) * 15.0);
        let p = [
            at[0] + c * x - s * y,
            at[1] + s * x + c * y,
            at[2] + (q[2] - lion.min[2]) * 15.0,
        ];
        // 8-bit values in the 16-bit fields, like autzen's: one colour depth for the set.
        put(&mut w, p, lion.rgb[k].map(|v| v >> 8));
    }
    written += lion_points;
    // Autzen copies, densified until the tile holds n points.
    let per_copy = autzen.xyz.len() as u64;
    let mut copy = 0u64;
    'fill: while written < n {
        let slot = copy % 4;
        let turned = rng.below(2) == 1;
        let lift = (rng.next_f64() - 0.5) * 30.0;
        let tint = [0, 1, 2].map(|_| 0.85 + rng.next_f64() * 0.3);
        let origin = [
            corner[0] + (slot % 2) as f64 * TILE[0] / 2.0,
            corner[1] + (slot / 2) as f64 * TILE[1] / 2.0,
        ];
        for k in 0..per_copy as usize {
            if written >= n {
                break 'fill;
            }
            let q = autzen.xyz[k];
            let (mut x, mut y) = (q[0] - autzen.min[0], q[1] - autzen.min[1]);
            if turned {
                x = (autzen.max[0] - autzen.min[0]) - x;
                y = (autzen.max[1] - autzen.min[1]) - y;
            }
            let p = [
                origin[0] + x + (rng.next_f64() - 0.5) * 2.5,
                origin[1] + y + (rng.next_f64() - 0.5) * 2.5,
                q[2] + lift + (rng.next_f64() - 0.5) * 0.4,
            ];
            let col = autzen.rgb[k];
            let tinted = [0, 1, 2].map(|a| (f64::from(col[a]) * tint[a]).min(255.0) as u16);
            put(&mut w, p, tinted);
            written += 1;
        }
        copy += 1;
    }
    w.close().unwrap();
}
