//! Per-voxel attribute channels, their quantization and the averaging rule for inner nodes.
//!
//! A scene stores only the channels its source has, each channel in its own block per treelet
//! (node `k` ↔ record `k`), so a client that does not draw a channel never reads or receives it.

use serde::{Deserialize, Serialize};

use crate::error::ProtoError;
use crate::limits::MAX_CHANNELS;

/// One attribute channel.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub enum Channel {
    /// sRGB colour, 8 bits per component (3 bytes).
    Color,
    /// Unit normal, octahedral encoding, 2 × 16-bit unorm (4 bytes).
    Normal,
    /// Scalar density of volume data normalised to the source's value range, 16-bit unorm (2 bytes).
    Density,
}

impl Channel {
    /// All channels, in canonical order.
    pub const ALL: [Channel; 3] = [Channel::Color, Channel::Normal, Channel::Density];

    /// Bytes per voxel.
    pub const fn size(self) -> usize {
        match self {
            Channel::Color => 3,
            Channel::Normal => 4,
            Channel::Density => 2,
        }
    }

    /// Stable short name used in keys and on the command line.
    pub const fn name(self) -> &'static str {
        match self {
            Channel::Color => "color",
            Channel::Normal => "normal",
            Channel::Density => "density",
        }
    }

    /// Number of f32 components of the dequantized value.
    pub const fn components(self) -> usize {
        match self {
            Channel::Color | Channel::Normal => 3,
            Channel::Density => 1,
        }
    }

    /// Dequantizes one record into `out[..components()]`.
    #[inline]
    pub fn decode(self, bytes: &[u8], out: &mut [f32]) {
        match self {
            Channel::Color => {
                for c in 0..3 {
                    out[c] = UNORM8[usize::from(bytes[c])];
                }
            }
            Channel::Normal => {
                let u = u16::from_le_bytes([bytes[0], bytes[1]]);
                let v = u16::from_le_bytes([bytes[2], bytes[3]]);
                out[..3].copy_from_slice(&oct_decode(u, v));
            }
            Channel::Density => {
                out[0] = f32::from(u16::from_le_bytes([bytes[0], bytes[1]])) / 65535.0;
            }
        }
    }

    /// Quantizes `value[..components()]` into one record. Non-finite input is clamped to a valid
    /// record (zero colour/density, +Z normal) so the output is always well formed.
    #[inline]
    pub fn encode(self, value: &[f32], out: &mut [u8]) {
        match self {
            Channel::Color => {
                for c in 0..3 {
                    out[c] = unorm8(value[c]);
                }
            }
            Channel::Normal => {
                let (u, v) = oct_encode([value[0], value[1], value[2]]);
                out[..2].copy_from_slice(&u.to_le_bytes());
                out[2..4].copy_from_slice(&v.to_le_bytes());
            }
            Channel::Density => {
                out[..2].copy_from_slice(&unorm16(value[0]).to_le_bytes());
            }
        }
    }

    /// The inner-node value for a set of child records: the f32 mean of the dequantized children
    /// (normals renormalised), quantized once (docs/design.md §2).
    ///
    /// One loop per channel kind (the build runs this for every inner node of a scene: a fifth
    /// of its store pass went to dispatching on the channel per child); the arithmetic is
    /// [`Channel::decode`]'s and [`Channel::encode`]'s, in the same order, so the result is
    /// bit-identical to decoding, summing and encoding.
    pub fn mean<'a>(self, children: impl IntoIterator<Item = &'a [u8]>, out: &mut [u8]) {
        let mut sum = [0f32; 3];
        let mut n = 0u32;
        match self {
            Channel::Color => {
                for c in children {
                    for k in 0..3 {
                        sum[k] += UNORM8[usize::from(c[k])];
                    }
                    n += 1;
                }
            }
            Channel::Normal => {
                for c in children {
                    let u = u16::from_le_bytes([c[0], c[1]]);
                    let v = u16::from_le_bytes([c[2], c[3]]);
                    let d = oct_decode(u, v);
                    for k in 0..3 {
                        sum[k] += d[k];
                    }
                    n += 1;
                }
            }
            Channel::Density => {
                for c in children {
                    sum[0] += f32::from(u16::from_le_bytes([c[0], c[1]])) / 65535.0;
                    n += 1;
                }
            }
        }
        if n > 0 {
            for s in sum.iter_mut() {
                *s /= n as f32;
            }
        }
        self.encode(&sum, out);
    }

    /// Stable one-byte id of the channel on the wire (`wire` frames and treelet messages):
    /// colour 0, normal 1, density 2. Never renumbered; new channels take new ids.
    pub const fn id(self) -> u8 {
        match self {
            Channel::Color => 0,
            Channel::Normal => 1,
            Channel::Density => 2,
        }
    }

    /// Inverse of [`Channel::id`]; `None` for an id this build does not know.
    pub const fn from_id(id: u8) -> Option<Channel> {
        match id {
            0 => Some(Channel::Color),
            1 => Some(Channel::Normal),
            2 => Some(Channel::Density),
            _ => None,
        }
    }

    /// Whether two records differ by at most one quantization step per component.
    pub fn within_one_step(self, a: &[u8], b: &[u8]) -> bool {
        match self {
            Channel::Color => (0..3).all(|c| a[c].abs_diff(b[c]) <= 1),
            Channel::Normal | Channel::Density => {
                a[..self.size()].chunks(2).zip(b.chunks(2)).all(|(x, y)| {
                    u16::from_le_bytes([x[0], x[1]]).abs_diff(u16::from_le_bytes([y[0], y[1]])) <= 1
                })
            }
        }
    }
}

/// `f32::from(b) / 255.0` for every byte, evaluated at compile time (the same IEEE division).
const UNORM8: [f32; 256] = {
    let mut t = [0f32; 256];
    let mut b = 0;
    while b < 256 {
        t[b] = b as f32 / 255.0;
        b += 1;
    }
    t
};

/// `w.round() as u32` (half away from zero) for finite `0 ≤ w < 2²⁴`, exactly: `w - trunc(w)`
/// is exact there. `f32::round` is a libm call on baseline x86-64, and quantizing attributes
/// was 4 % of a point import.
#[inline]
fn round_unsigned(w: f32) -> u32 {
    let whole = w as u32;
    if w - whole as f32 >= 0.5 {
        whole + 1
    } else {
        whole
    }
}

#[inline]
fn unorm8(v: f32) -> u8 {
    if v.is_finite() {
        round_unsigned(v.clamp(0.0, 1.0) * 255.0) as u8
    } else {
        0
    }
}

#[inline]
fn unorm16(v: f32) -> u16 {
    if v.is_finite() {
        round_unsigned(v.clamp(0.0, 1.0) * 65535.0) as u16
    } else {
        0
    }
}

/// Octahedral normal encoding into two 16-bit unorms. A zero or non-finite vector encodes +Z.
#[inline]
pub fn oct_encode(n: [f32; 3]) -> (u16, u16) {
    let l1 = n[0].abs() + n[1].abs() + n[2].abs();
    if !(l1.is_finite() && l1 > 1e-20) {
        return oct_encode([0.0, 0.0, 1.0]);
    }
    let (mut x, mut y) = (n[0] / l1, n[1] / l1);
    if n[2] < 0.0 {
        let (ox, oy) = (x, y);
        x = (1.0 - oy.abs()) * if ox >= 0.0 { 1.0 } else { -1.0 };
        y = (1.0 - ox.abs()) * if oy >= 0.0 { 1.0 } else { -1.0 };
    }
    let q = |v: f32| round_unsigned((v.clamp(-1.0, 1.0) * 0.5 + 0.5) * 65535.0) as u16;
    (q(x), q(y))
}

/// Inverse of [`oct_encode`]; always returns a unit vector.
#[inline]
pub fn oct_decode(u: u16, v: u16) -> [f32; 3] {
    let x = f32::from(u) / 65535.0 * 2.0 - 1.0;
    let y = f32::from(v) / 65535.0 * 2.0 - 1.0;
    let z = 1.0 - x.abs() - y.abs();
    let (mut x, mut y) = (x, y);
    if z < 0.0 {
        let (ox, oy) = (x, y);
        x = (1.0 - oy.abs()) * if ox >= 0.0 { 1.0 } else { -1.0 };
        y = (1.0 - ox.abs()) * if oy >= 0.0 { 1.0 } else { -1.0 };
    }
    let len = (x * x + y * y + z * z).sqrt();
    [x / len, y / len, z / len]
}

/// The channels a scene stores, in canonical order, each at most once.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct AttributeLayout {
    channels: Vec<Channel>,
}

impl AttributeLayout {
    /// Builds a layout; duplicates are removed and channels sorted into canonical order.
    pub fn new(channels: impl IntoIterator<Item = Channel>) -> Self {
        let mut channels: Vec<_> = channels.into_iter().collect();
        channels.sort();
        channels.dedup();
        Self { channels }
    }

    /// The stored channels, in layout order.
    pub fn channels(&self) -> &[Channel] {
        &self.channels
    }

    /// The scene stores channel `c`.
    pub fn contains(&self, c: Channel) -> bool {
        self.channels.contains(&c)
    }

    /// Position of a channel in this layout.
    pub fn index_of(&self, c: Channel) -> Option<usize> {
        self.channels.iter().position(|&x| x == c)
    }

    /// Bytes per voxel over all channels.
    pub fn bytes_per_voxel(&self) -> usize {
        self.channels.iter().map(|c| c.size()).sum()
    }

    /// Checks a decoded layout against the limits.
    pub fn validate(&self) -> Result<(), ProtoError> {
        if self.channels.len() > MAX_CHANNELS {
            return Err(ProtoError::TooLarge {
                what: "attribute layout",
                len: self.channels.len(),
                limit: MAX_CHANNELS,
            });
        }
        if self.channels.windows(2).any(|w| w[0] >= w[1]) {
            return Err(ProtoError::OutOfRange {
                what: "attribute layout",
                detail: "channels not unique and in canonical order".into(),
            });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn unsigned_rounding_equals_round_half_away_from_zero() {
        let below_half = 0.5f32.next_down();
        let mut edges = vec![
            0.0,
            below_half,
            0.5,
            0.5f32.next_up(),
            1.5,
            2.5,
            254.5,
            65534.5,
        ];
        edges.extend([255.0f32, 65535.0].iter().flat_map(|&v| [v.next_down(), v]));
        for k in 0..=65535u32 {
            let w = k as f32;
            edges.extend([w, w + 0.5, (w + 0.5).next_down(), (w + 0.5).next_up()]);
        }
        let mut rng = crate::rng::SplitMix64::new(11);
        edges.extend((0..200_000).map(|_| rng.next_f64() as f32 * 65535.0));
        for w in edges {
            assert_eq!(round_unsigned(w), w.round() as u32, "{w:e}");
        }
    }

    #[test]
    fn octahedral_round_trip_is_close() {
        for n in [
            [0.0, 0.0, 1.0],
            [0.0, 0.0, -1.0],
            [1.0, 0.0, 0.0],
            [-0.6, 0.0, -0.8],
            [0.577, -0.577, 0.577],
        ] {
            let (u, v) = oct_encode(n);
            let d = oct_decode(u, v);
            let dot: f32 = (0..3).map(|i| d[i] * n[i]).sum::<f32>()
                / (n.iter().map(|x| x * x).sum::<f32>().sqrt());
            assert!(dot > 0.99999, "{n:?} -> {d:?}");
        }
        assert_eq!(
            oct_decode(oct_encode([0.0; 3]).0, oct_encode([0.0; 3]).1)[2],
            1.0
        );
        let nan = oct_encode([f32::NAN, 0.0, 1.0]);
        assert!(oct_decode(nan.0, nan.1).iter().all(|x| x.is_finite()));
    }

    #[test]
    fn mean_of_colours_rounds_once() {
        let a = [10u8, 20, 30];
        let b = [11u8, 20, 255];
        let mut out = [0u8; 3];
        Channel::Color.mean([&a[..], &b[..]], &mut out);
        assert_eq!(out, [11, 20, 143]);
    }

    #[test]
    fn layout_is_canonical() {
        let l = AttributeLayout::new([Channel::Normal, Channel::Color, Channel::Normal]);
        assert_eq!(l.channels(), &[Channel::Color, Channel::Normal]);
        assert_eq!(l.bytes_per_voxel(), 7);
        assert!(l.validate().is_ok());
    }

    #[test]
    fn channel_ids_round_trip() {
        for c in Channel::ALL {
            assert_eq!(Channel::from_id(c.id()), Some(c));
        }
        assert!((3..=u8::MAX).all(|id| Channel::from_id(id).is_none()));
    }

    /// The mean as first written: decode each child, sum, divide, encode.
    fn mean_by_decoding(c: Channel, children: &[Vec<u8>]) -> Vec<u8> {
        let mut sum = [0f32; 3];
        let mut tmp = [0f32; 3];
        for child in children {
            c.decode(child, &mut tmp);
            for k in 0..c.components() {
                sum[k] += tmp[k];
            }
        }
        if !children.is_empty() {
            for s in sum.iter_mut() {
                *s /= children.len() as f32;
            }
        }
        let mut out = vec![0u8; c.size()];
        c.encode(&sum, &mut out);
        out
    }

    #[test]
    fn the_colour_table_is_the_division() {
        for b in 0..=255u8 {
            assert_eq!(
                UNORM8[usize::from(b)].to_bits(),
                (f32::from(b) / 255.0).to_bits()
            );
        }
    }

    proptest! {
        #[test]
        fn mean_is_bit_identical_to_decode_sum_encode(
            channel in 0usize..3,
            children in proptest::collection::vec(proptest::collection::vec(any::<u8>(), 4), 0..9),
        ) {
            let c = Channel::ALL[channel];
            let children: Vec<Vec<u8>> = children.into_iter().map(|v| v[..c.size()].to_vec()).collect();
            let mut out = vec![0u8; c.size()];
            c.mean(children.iter().map(|v| v.as_slice()), &mut out);
            prop_assert_eq!(out, mean_by_decoding(c, &children));
        }

        #[test]
        fn normal_decode_is_unit(u in any::<u16>(), v in any::<u16>()) {
            let d = oct_decode(u, v);
            let len = (d[0]*d[0] + d[1]*d[1] + d[2]*d[2]).sqrt();
            prop_assert!((len - 1.0).abs() < 1e-5);
        }
    }
}
