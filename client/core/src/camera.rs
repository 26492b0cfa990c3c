//! Pinhole cameras and the scripted camera paths of headless runs.
//!
//! A [`Camera`] turns continuous pixel coordinates into world-space [`Ray`]s for the ray caster
//! and the analysis pass, and gives the per-pixel angle the LOD test needs. A [`CameraPath`]
//! says where the camera is in each client *cycle*: runs are compared by cycle, not by wall
//! time, so the same path, seed and frame give bit-identical cameras on every machine.

use std::f64::consts::{PI, TAU};
use std::fmt;
use std::str::FromStr;

pub use arbor_proto::rng::SplitMix64;
use glam::DVec3;

use crate::incore::SceneFrame;
use crate::traverse::Ray;

/// Largest frame side accepted by [`Camera::look_at`].
pub const MAX_FRAME_SIDE: u32 = 16384;
/// Vertical field of view of the cameras made by [`CameraPath`] (50°).
pub const DEFAULT_FOV_Y: f64 = 50.0 * PI / 180.0;
/// Distance of the static and orbiting cameras from the scene centre, in scene edges.
pub const DEFAULT_DISTANCE_FACTOR: f64 = 1.6;
/// Largest elevation of seeded viewing directions (±35°), so no path starts looking straight
/// down the up axis.
pub const MAX_ELEVATION: f64 = 35.0 * PI / 180.0;
/// World up of [`CameraPath`] cameras: +Z, as in the geospatial scans.
pub const WORLD_UP: DVec3 = DVec3::Z;

/// Why a camera could not be made.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum CameraError {
    /// A position, target or direction has a NaN or infinite component.
    #[error("camera {what} is not finite")]
    NotFinite {
        /// Which input: position, target, up.
        what: &'static str,
    },
    /// Width or height is zero.
    #[error("frame {width}×{height} has no pixels")]
    EmptyFrame {
        /// Frame width, pixels.
        width: u32,
        /// Frame height, pixels.
        height: u32,
    },
    /// A side is above [`MAX_FRAME_SIDE`].
    #[error("frame {width}×{height} is larger than {MAX_FRAME_SIDE}×{MAX_FRAME_SIDE}")]
    FrameTooLarge {
        /// Frame width, pixels.
        width: u32,
        /// Frame height, pixels.
        height: u32,
    },
    /// The camera looks at its own position: no direction.
    #[error("camera target equals its position")]
    TargetIsPosition,
    /// The vertical field of view (radians) is not in (0, π).
    #[error("vertical field of view {0} rad is not in (0, π)")]
    FieldOfView(f64),
}

/// A pinhole camera. `forward` and `up` are orthonormal.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// Eye position, world units.
    pub position: DVec3,
    /// Unit view direction.
    pub forward: DVec3,
    /// Unit up direction, orthogonal to `forward`.
    pub up: DVec3,
    /// Vertical field of view in radians.
    pub fov_y: f64,
    /// Frame width, pixels.
    pub width: u32,
    /// Frame height, pixels.
    pub height: u32,
}

impl Camera {
    /// A camera at `position` looking at `target`, `up_hint` giving the upward screen
    /// direction. When `up_hint` is zero or parallel to the view direction, the world axis
    /// least aligned with the view direction is used instead.
    pub fn look_at(
        position: DVec3,
        target: DVec3,
        up_hint: DVec3,
        fov_y: f64,
        width: u32,
        height: u32,
    ) -> Result<Camera, CameraError> {
        for (what, v) in [
            ("position", position),
            ("target", target),
            ("up hint", up_hint),
        ] {
            if !v.is_finite() {
                return Err(CameraError::NotFinite { what });
            }
        }
        if width == 0 || height == 0 {
            return Err(CameraError::EmptyFrame { width, height });
        }
        if width > MAX_FRAME_SIDE || height > MAX_FRAME_SIDE {
            return Err(CameraError::FrameTooLarge { width, height });
        }
        if !(fov_y > 0.0 && fov_y < PI) {
            return Err(CameraError::FieldOfView(fov_y));
        }
        let forward = (target - position).try_normalize();
        let Some(forward) = forward else {
            return Err(if target == position {
                CameraError::TargetIsPosition
            } else {
                // The difference overflowed or underflowed.
                CameraError::NotFinite {
                    what: "view direction",
                }
            });
        };
        Ok(Camera {
            position,
            forward,
            up: orthonormal_up(forward, up_hint),
            fov_y,
            width,
            height,
        })
    }

    /// Screen-right unit vector.
    pub fn right(&self) -> DVec3 {
        self.forward.cross(self.up)
    }

    /// The ray through continuous pixel coordinates `(px, py)`: pixel `(x, y)`'s centre is
    /// `(x + 0.5, y + 0.5)`, `y` grows downward. The direction has unit length. For many rays
    /// of one camera, [`Camera::pixel_rays`] computes what they share once.
    pub fn ray(&self, px: f64, py: f64) -> Ray {
        self.pixel_rays().ray(px, py)
    }

    /// The rays of this camera, with what every ray shares (the tangent of the half field of
    /// view, the aspect, the right vector) computed once; bit for bit [`Camera::ray`].
    pub fn pixel_rays(&self) -> PixelRays {
        PixelRays {
            origin: self.position,
            forward: self.forward,
            right: self.right(),
            up: self.up,
            tan_half_fov_y: (self.fov_y * 0.5).tan(),
            aspect: f64::from(self.width) / f64::from(self.height),
            width: f64::from(self.width),
            height: f64::from(self.height),
        }
    }

    /// Angle of one pixel at the image centre: `2·tan(fov_y/2)/height`.
    pub fn pixel_angle(&self) -> f64 {
        2.0 * (self.fov_y * 0.5).tan() / f64::from(self.height)
    }
}

/// The rays of one [`Camera`] ([`Camera::pixel_rays`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PixelRays {
    origin: DVec3,
    forward: DVec3,
    right: DVec3,
    up: DVec3,
    tan_half_fov_y: f64,
    aspect: f64,
    width: f64,
    height: f64,
}

impl PixelRays {
    /// The ray through continuous pixel coordinates `(px, py)`, as [`Camera::ray`] says.
    pub fn ray(&self, px: f64, py: f64) -> Ray {
        let h = self.tan_half_fov_y;
        let sx = (2.0 * px / self.width - 1.0) * h * self.aspect;
        let sy = (1.0 - 2.0 * py / self.height) * h;
        let dir = (self.forward + self.right * sx + self.up * sy).normalize_or_zero();
        Ray {
            origin: self.origin,
            dir,
        }
    }
}

/// The unit vector of `hint` orthogonal to `forward` (unit), falling back to the world axis
/// least aligned with `forward` when `hint` is degenerate.
fn orthonormal_up(forward: DVec3, hint: DVec3) -> DVec3 {
    let project = |h: DVec3| (h - forward * forward.dot(h)).try_normalize();
    if let Some(up) = project(hint).filter(|_| hint.normalize_or_zero().dot(forward).abs() < 0.9999)
    {
        return up;
    }
    let a = forward.abs();
    let axis = if a.x <= a.y && a.x <= a.z {
        DVec3::X
    } else if a.y <= a.z {
        DVec3::Y
    } else {
        DVec3::Z
    };
    // `axis` is at most 1/√3 aligned with a unit `forward`, so this cannot fail.
    project(axis).unwrap_or(DVec3::Y)
}

/// Where the camera is in each cycle of a run; every camera looks at the scene centre.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum CameraPath {
    /// A seeded viewpoint, fixed.
    Static,
    /// The seeded viewpoint, turning about the world up axis by `degrees_per_cycle` per cycle.
    Orbit {
        /// Turn per cycle, degrees.
        degrees_per_cycle: f64,
    },
    /// Along the seeded direction from 3 edges to 0.6 edge from the centre (close to the
    /// bounding cube's faces, inside its corners), linear in log-distance over `cycles`, then
    /// holding.
    FlyIn {
        /// Cycles the approach takes.
        cycles: u32,
    },
    /// Every `every` cycles, a new seeded random viewpoint on a sphere of 1.5 edges.
    Jump {
        /// Cycles between jumps.
        every: u32,
    },
    /// A fixed camera at `eye` looking at `target`, both in scene edges from the scene
    /// centre (so the same text means the same view of a scene wherever its coordinates lie);
    /// what the viewer's `C` key prints.
    Look {
        /// Eye position, edges from the centre.
        eye: [f64; 3],
        /// A point the camera looks at, edges from the centre; not `eye`.
        target: [f64; 3],
    },
}

/// A camera path the command line could not read.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error(
    "camera path {input:?}: {reason} (expected static, orbit:DEG, fly-in:CYCLES, jump:EVERY or \
     look:EX,EY,EZ:TX,TY,TZ)"
)]
pub struct ParsePathError {
    /// The text as given.
    pub input: String,
    /// What is wrong with it.
    pub reason: String,
}

impl CameraPath {
    /// Reads `static`, `orbit:DEG`, `fly-in:CYCLES`, `jump:EVERY` (`CYCLES`, `EVERY` ≥ 1) or
    /// `look:EX,EY,EZ:TX,TY,TZ` (finite, in scene edges from the centre, the eye not the
    /// target).
    pub fn parse(s: &str) -> Result<CameraPath, ParsePathError> {
        let err = |reason: &str| ParsePathError {
            input: s.to_owned(),
            reason: reason.to_owned(),
        };
        let count = |v: &str, what: &str| match v.parse::<u32>() {
            Ok(n) if n >= 1 => Ok(n),
            _ => Err(err(&format!("{what} must be a whole number ≥ 1"))),
        };
        let (kind, value) = match s.split_once(':') {
            Some((k, v)) => (k, Some(v)),
            None => (s, None),
        };
        match (kind, value) {
            ("static", None) => Ok(CameraPath::Static),
            ("orbit", Some(v)) => match v.parse::<f64>() {
                Ok(d) if d.is_finite() => Ok(CameraPath::Orbit {
                    degrees_per_cycle: d,
                }),
                _ => Err(err("degrees per cycle must be a finite number")),
            },
            ("fly-in", Some(v)) => Ok(CameraPath::FlyIn {
                cycles: count(v, "cycles")?,
            }),
            ("jump", Some(v)) => Ok(CameraPath::Jump {
                every: count(v, "jump interval")?,
            }),
            ("look", Some(v)) => {
                let triple = |t: &str| -> Option<[f64; 3]> {
                    let mut it = t.split(',').map(|c| c.trim().parse::<f64>().ok());
                    let xyz = [it.next()??, it.next()??, it.next()??];
                    (it.next().is_none() && xyz.iter().all(|c| c.is_finite())).then_some(xyz)
                };
                let parsed = v
                    .split_once(':')
                    .and_then(|(e, t)| Some((triple(e)?, triple(t)?)));
                let Some((eye, target)) = parsed else {
                    return Err(err("look takes two points of three finite numbers"));
                };
                if eye == target {
                    return Err(err("the eye is the target"));
                }
                Ok(CameraPath::Look { eye, target })
            }
            ("static", Some(_)) => Err(err("static takes no value")),
            ("orbit" | "fly-in" | "jump" | "look", None) => Err(err("missing value after ':'")),
            _ => Err(err("unknown path kind")),
        }
    }

    /// The camera at `cycle`, at [`DEFAULT_DISTANCE_FACTOR`] for static and orbiting paths.
    pub fn camera(
        &self,
        cycle: u32,
        frame: &SceneFrame,
        seed: u64,
        width: u32,
        height: u32,
    ) -> Camera {
        self.camera_at_distance(cycle, frame, seed, width, height, DEFAULT_DISTANCE_FACTOR)
    }

    /// The camera at `cycle`; static and orbiting cameras stand `distance_factor` edges from
    /// the scene centre. A pure function of its arguments. `width` and `height` are clamped to
    /// `1..=MAX_FRAME_SIDE`; a non-finite frame gives a camera whose rays hit nothing.
    pub fn camera_at_distance(
        &self,
        cycle: u32,
        frame: &SceneFrame,
        seed: u64,
        width: u32,
        height: u32,
        distance_factor: f64,
    ) -> Camera {
        let centre = DVec3::from_array(frame.centre());
        let edge = frame.edge;
        let mut rng = SplitMix64::new(seed);
        let azimuth = rng.next_f64() * TAU;
        let elevation = (rng.next_f64() * 2.0 - 1.0) * MAX_ELEVATION;
        let (dir, distance) = match *self {
            CameraPath::Look { eye, target } => {
                let at = |p: [f64; 3]| centre + DVec3::from_array(p) * edge;
                return looking(at(eye), at(target), width, height);
            }
            CameraPath::Static => (spherical(azimuth, elevation), distance_factor * edge),
            CameraPath::Orbit { degrees_per_cycle } => {
                // Reduce the angle in degrees first so long runs keep full precision.
                let turn = (f64::from(cycle) * degrees_per_cycle).rem_euclid(360.0);
                (
                    spherical(azimuth + turn.to_radians(), elevation),
                    distance_factor * edge,
                )
            }
            CameraPath::FlyIn { cycles } => {
                let s = (f64::from(cycle) / f64::from(cycles.max(1))).min(1.0);
                let (far, near) = ((3.0 * edge).ln(), (0.6 * edge).ln());
                (
                    spherical(azimuth, elevation),
                    (far + (near - far) * s).exp(),
                )
            }
            CameraPath::Jump { every } => {
                let k = cycle / every.max(1);
                let mut jump = SplitMix64::new(seed ^ SplitMix64::new(u64::from(k)).next_u64());
                // Uniform on the sphere: z uniform in [-1, 1], azimuth uniform.
                let z = jump.next_f64() * 2.0 - 1.0;
                let phi = jump.next_f64() * TAU;
                let r = (1.0 - z * z).max(0.0).sqrt();
                (DVec3::new(r * phi.cos(), r * phi.sin(), z), 1.5 * edge)
            }
        };
        looking(centre + dir * distance, centre, width, height)
    }

    /// The [`CameraPath::Look`] path of a camera, in the edges of `frame` (the inverse of
    /// [`CameraPath::camera`] for it, up to rounding): the target is one edge ahead.
    pub fn look_of(camera: &Camera, frame: &SceneFrame) -> CameraPath {
        let centre = DVec3::from_array(frame.centre());
        let eye = (camera.position - centre) / frame.edge;
        CameraPath::Look {
            eye: eye.to_array(),
            target: (eye + camera.forward).to_array(),
        }
    }
}

/// A path's camera at `position` looking at `target` (straight down -Y when they coincide or
/// are not finite), up towards [`WORLD_UP`], `width` and `height` clamped.
fn looking(position: DVec3, target: DVec3, width: u32, height: u32) -> Camera {
    let forward = (target - position).try_normalize().unwrap_or(-DVec3::Y);
    Camera {
        position,
        forward,
        up: orthonormal_up(forward, WORLD_UP),
        fov_y: DEFAULT_FOV_Y,
        width: width.clamp(1, MAX_FRAME_SIDE),
        height: height.clamp(1, MAX_FRAME_SIDE),
    }
}

impl FromStr for CameraPath {
    type Err = ParsePathError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        CameraPath::parse(s)
    }
}

impl fmt::Display for CameraPath {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            CameraPath::Static => f.write_str("static"),
            CameraPath::Orbit { degrees_per_cycle } => write!(f, "orbit:{degrees_per_cycle}"),
            CameraPath::FlyIn { cycles } => write!(f, "fly-in:{cycles}"),
            CameraPath::Jump { every } => write!(f, "jump:{every}"),
            // Debug's digits: the shortest that read back exactly, with an exponent where long.
            CameraPath::Look { eye, target } => write!(
                f,
                "look:{:?},{:?},{:?}:{:?},{:?},{:?}",
                eye[0], eye[1], eye[2], target[0], target[1], target[2]
            ),
        }
    }
}

/// Unit vector at `azimuth` about +Z from +X and `elevation` above the XY plane.
pub fn spherical(azimuth: f64, elevation: f64) -> DVec3 {
    DVec3::new(
        elevation.cos() * azimuth.cos(),
        elevation.cos() * azimuth.sin(),
        elevation.sin(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame() -> SceneFrame {
        SceneFrame {
            origin: [10.0, -4.0, 2.0],
            edge: 8.0,
            max_depth: 6,
        }
    }

    #[test]
    fn look_at_rejects_bad_input() {
        let p = DVec3::ZERO;
        let t = DVec3::X;
        let fov = 1.0;
        assert!(Camera::look_at(p, t, DVec3::Z, fov, 64, 64).is_ok());
        assert_eq!(
            Camera::look_at(p, p, DVec3::Z, fov, 64, 64),
            Err(CameraError::TargetIsPosition)
        );
        assert!(matches!(
            Camera::look_at(DVec3::splat(f64::NAN), t, DVec3::Z, fov, 64, 64),
            Err(CameraError::NotFinite { .. })
        ));
        assert!(matches!(
            Camera::look_at(
                p,
                DVec3::new(f64::INFINITY, 0.0, 0.0),
                DVec3::Z,
                fov,
                64,
                64
            ),
            Err(CameraError::NotFinite { .. })
        ));
        assert!(matches!(
            Camera::look_at(p, t, DVec3::Z, fov, 0, 64),
            Err(CameraError::EmptyFrame { .. })
        ));
        assert!(matches!(
            Camera::look_at(p, t, DVec3::Z, fov, 16385, 64),
            Err(CameraError::FrameTooLarge { .. })
        ));
        for bad in [0.0, PI, -1.0, f64::NAN, 4.0] {
            assert!(matches!(
                Camera::look_at(p, t, DVec3::Z, bad, 64, 64),
                Err(CameraError::FieldOfView(_))
            ));
        }
        // Up hint parallel to the view direction: a fallback, still orthonormal.
        let c = Camera::look_at(p, t, DVec3::X, fov, 64, 64).unwrap();
        assert!(c.up.dot(c.forward).abs() < 1e-12);
        assert!((c.up.length() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn rays_through_centre_and_corners() {
        let c = Camera::look_at(
            DVec3::ZERO,
            DVec3::new(0.0, 0.0, -5.0),
            DVec3::Y,
            PI / 2.0,
            200,
            100,
        )
        .unwrap();
        let r = c.ray(100.0, 50.0);
        assert!((r.dir - DVec3::new(0.0, 0.0, -1.0)).length() < 1e-15);
        // Top edge is tan(45°) = 1 up, y grows downward.
        let top = c.ray(100.0, 0.0);
        assert!((top.dir - DVec3::new(0.0, 1.0, -1.0).normalize()).length() < 1e-15);
        // Right edge: aspect 2.
        let right = c.ray(200.0, 50.0);
        assert!((right.dir - DVec3::new(2.0, 0.0, -1.0).normalize()).length() < 1e-15);
        for (x, y) in [(0.5, 0.5), (199.5, 99.5), (3.25, 77.0)] {
            assert!((c.ray(x, y).dir.length() - 1.0).abs() < 1e-15);
        }
        assert!((c.pixel_angle() - 2.0 / 100.0).abs() < 1e-15);
    }

    #[test]
    fn parse_round_trips_and_rejects() {
        for s in [
            "static",
            "orbit:2.5",
            "orbit:-1",
            "fly-in:30",
            "jump:4",
            "look:1.6,0.0,0.25:0.0,0.0,0.0",
            "look:-0.1,2e-7,0.3333333333333333:1e300,-4.0,5.0",
        ] {
            let p = CameraPath::parse(s).unwrap();
            assert_eq!(p.to_string(), s);
            assert_eq!(s.parse::<CameraPath>().unwrap(), p);
        }
        for s in [
            "",
            "orbit",
            "orbit:",
            "orbit:x",
            "orbit:inf",
            "fly-in:0",
            "fly-in:-3",
            "jump:",
            "jump:1.5",
            "static:1",
            "spin:3",
            "Static",
            "look",
            "look:1,2,3",
            "look:1,2:3,4",
            "look:1,2,3:4,5,6,7",
            "look:1,2,3:4,5,NaN",
            "look:1,2,inf:4,5,6",
            "look:1,2,3:1,2,3",
            "look:1,2,3:4,5,6:7,8,9",
        ] {
            let e = CameraPath::parse(s).unwrap_err();
            assert!(e.to_string().contains("expected static"), "{e}");
        }
    }

    #[test]
    fn a_look_path_is_its_points_in_edges_from_the_centre_and_inverts() {
        let f = frame();
        let centre = DVec3::from_array(f.centre());
        // Whole numbers and spaces after commas are read too.
        let path = CameraPath::parse("look:1.5, -0.5, 0.25:0.1,0,0").unwrap();
        for cycle in [0, 7, 1000] {
            let c = path.camera(cycle, &f, 99, 64, 48);
            assert_eq!(c.position, centre + DVec3::new(1.5, -0.5, 0.25) * f.edge);
            let to_target = centre + DVec3::new(0.1, 0.0, 0.0) * f.edge - c.position;
            assert!((c.forward - to_target.normalize()).length() < 1e-15);
            assert!(c.up.dot(c.forward).abs() < 1e-15 && c.up.z > 0.0);
            assert_eq!((c.width, c.height), (64, 48));
        }
        // Any camera, printed as a look path and read back, is the same view up to rounding,
        // in a scene far from the origin too.
        let far = SceneFrame {
            origin: [6.4e6, -2.1e6, 310.0],
            edge: 1024.0,
            max_depth: 20,
        };
        for seed in 0..20 {
            for f in [frame(), far] {
                let c = CameraPath::Jump { every: 1 }.camera(seed, &f, seed.into(), 32, 32);
                let text = CameraPath::look_of(&c, &f).to_string();
                let back = CameraPath::parse(&text).unwrap().camera(0, &f, 0, 32, 32);
                let tolerance = 1e-12 * f.edge.max(c.position.abs().max_element());
                assert!((back.position - c.position).length() <= tolerance, "{text}");
                assert!((back.forward - c.forward).length() < 1e-12, "{text}");
            }
        }
    }

    #[test]
    fn paths_are_deterministic_and_look_at_the_centre() {
        let f = frame();
        let centre = DVec3::from_array(f.centre());
        for path in [
            CameraPath::Static,
            CameraPath::Orbit {
                degrees_per_cycle: 3.0,
            },
            CameraPath::FlyIn { cycles: 10 },
            CameraPath::Jump { every: 5 },
        ] {
            for cycle in [0, 1, 7, 1000] {
                let a = path.camera(cycle, &f, 42, 320, 240);
                let b = path.camera(cycle, &f, 42, 320, 240);
                assert_eq!(a, b);
                let to_centre = (centre - a.position).normalize();
                assert!((to_centre - a.forward).length() < 1e-12, "{path} {cycle}");
                assert!(a.up.dot(a.forward).abs() < 1e-12);
            }
        }
        let s0 = CameraPath::Static.camera(0, &f, 1, 64, 64);
        assert_eq!(s0, CameraPath::Static.camera(99, &f, 1, 64, 64));
        assert_ne!(s0, CameraPath::Static.camera(0, &f, 2, 64, 64));
        let d = (s0.position - centre).length();
        assert!((d - 1.6 * f.edge).abs() < 1e-9);
        let el = ((s0.position - centre).z / d).asin();
        assert!(el.abs() <= MAX_ELEVATION + 1e-12);
    }

    #[test]
    fn fly_in_is_log_linear_then_holds() {
        let f = frame();
        let centre = DVec3::from_array(f.centre());
        let path = CameraPath::FlyIn { cycles: 4 };
        let dist = |c| (path.camera(c, &f, 3, 64, 64).position - centre).length();
        assert!((dist(0) - 3.0 * f.edge).abs() < 1e-9);
        assert!((dist(4) - 0.6 * f.edge).abs() < 1e-9);
        assert_eq!(dist(4), dist(50));
        // Geometric mean at the midpoint.
        assert!((dist(2) - (3.0f64 * 0.6).sqrt() * f.edge).abs() < 1e-9);
    }

    #[test]
    fn orbit_turns_and_jump_jumps() {
        let f = frame();
        let centre = DVec3::from_array(f.centre());
        let orbit = CameraPath::Orbit {
            degrees_per_cycle: 90.0,
        };
        let a = orbit.camera(0, &f, 9, 64, 64).position - centre;
        let b = orbit.camera(1, &f, 9, 64, 64).position - centre;
        assert!((a.z - b.z).abs() < 1e-9);
        assert!(a.truncate().dot(b.truncate()).abs() < 1e-9);
        let jump = CameraPath::Jump { every: 3 };
        let p = |c| jump.camera(c, &f, 9, 64, 64).position;
        assert_eq!(p(0), p(2));
        assert_ne!(p(2), p(3));
        assert_eq!(p(3), p(5));
        assert!(((p(4) - centre).length() - 1.5 * f.edge).abs() < 1e-9);
    }
}
