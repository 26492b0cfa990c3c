//! Camera controls of the window viewer, as plain data: input in, [`Camera`] out.
//!
//! The window code translates winit events into the calls here ([`Controls::button`],
//! [`Controls::cursor`], [`Controls::wheel`], [`Controls::key`], [`Controls::toggle_mode`]) and
//! asks for [`Controls::camera`] each frame after [`Controls::advance`]; nothing here knows about
//! windows, so every behaviour is unit-tested.
//!
//! * **Orbit** (the start mode): left-drag turns the camera about the scene centre (azimuth about
//!   [`WORLD_UP`], elevation clamped short of the poles), the wheel moves it towards or away
//!   from the centre in log distance; the camera always looks at the centre.
//! * **Fly**: `W`/`S` forward and back, `A`/`D` left and right, `E`/`Q` up and down (world up),
//!   at [`FLY_SPEED`] scene edges per second; right-drag turns the view direction.
//! * `Tab` toggles; returning to orbit turns the camera back towards the centre.
//!
//! The start pose is [`CameraPath::Static`]'s camera for the same seed, bit for bit, so the
//! window and a headless render of "the same camera" agree until the user moves.

use std::f64::consts::FRAC_PI_2;

use glam::DVec3;

use arbor_client_core::camera::{Camera, CameraPath, MAX_FRAME_SIDE, WORLD_UP, spherical};
use arbor_client_core::incore::SceneFrame;

/// Orbit and look rotation per pixel of mouse movement, radians.
pub const ROTATE_PER_PIXEL: f64 = 0.005;
/// Change of log distance per wheel line (one notch moves ~10 % closer).
pub const ZOOM_PER_LINE: f64 = 0.1;
/// Fly speed, scene edges per second.
pub const FLY_SPEED: f64 = 0.4;
/// Orbit distance limits, in scene edges.
pub const MIN_DISTANCE: f64 = 0.02;
pub const MAX_DISTANCE: f64 = 50.0;
/// Largest elevation of the orbit and pitch of the fly camera (just short of the poles, where
/// the up vector would be undefined).
pub const MAX_PITCH: f64 = FRAC_PI_2 - 0.01;

/// Control mode.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mode {
    Orbit,
    Fly,
}

impl Mode {
    pub fn name(self) -> &'static str {
        match self {
            Mode::Orbit => "orbit",
            Mode::Fly => "fly",
        }
    }
}

/// A held movement key of fly mode.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Move {
    Forward,
    Back,
    Left,
    Right,
    Up,
    Down,
}

impl Move {
    const ALL: [Move; 6] = [
        Move::Forward,
        Move::Back,
        Move::Left,
        Move::Right,
        Move::Up,
        Move::Down,
    ];

    fn index(self) -> usize {
        self as usize
    }
}

/// A mouse button that drags.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Button {
    Left,
    Right,
}

/// Camera state driven by input.
#[derive(Clone, Debug)]
pub struct Controls {
    mode: Mode,
    centre: DVec3,
    edge: f64,
    /// Position, orientation and field of view; its frame size is replaced by
    /// [`camera`](Self::camera)'s.
    pose: Camera,
    held: [bool; 6],
    drag: Option<Button>,
    cursor: Option<(f64, f64)>,
    moved: bool,
}

impl Controls {
    /// Controls starting at [`CameraPath::Static`]'s camera for `seed`, in orbit mode.
    pub fn new(frame: &SceneFrame, seed: u64) -> Self {
        Self::starting_at(frame, &CameraPath::Static, seed)
    }

    /// Controls starting at `path`'s first camera for `seed`, in orbit mode (orbiting the
    /// scene centre).
    pub fn starting_at(frame: &SceneFrame, path: &CameraPath, seed: u64) -> Self {
        Self {
            mode: Mode::Orbit,
            centre: DVec3::from_array(frame.centre()),
            edge: frame.edge,
            pose: path.camera(0, frame, seed, 1, 1),
            held: [false; 6],
            drag: None,
            cursor: None,
            moved: false,
        }
    }

    pub fn mode(&self) -> Mode {
        self.mode
    }

    /// Whether the camera ever left its start pose.
    pub fn moved(&self) -> bool {
        self.moved
    }

    /// The camera for a `width × height` frame (each side clamped to `1..=MAX_FRAME_SIDE`).
    pub fn camera(&self, width: u32, height: u32) -> Camera {
        Camera {
            width: width.clamp(1, MAX_FRAME_SIDE),
            height: height.clamp(1, MAX_FRAME_SIDE),
            ..self.pose
        }
    }

    /// `Tab`: orbit ↔ fly. Entering orbit turns the camera towards the scene centre.
    pub fn toggle_mode(&mut self) {
        self.mode = match self.mode {
            Mode::Orbit => Mode::Fly,
            Mode::Fly => {
                self.look_from(self.pose.position, self.centre);
                Mode::Orbit
            }
        };
        self.drag = None;
    }

    /// A movement key pressed or released (used in fly mode).
    pub fn key(&mut self, key: Move, pressed: bool) {
        self.held[key.index()] = pressed;
    }

    /// Forgets held keys and drags (the window lost focus).
    pub fn release_all(&mut self) {
        self.held = [false; 6];
        self.drag = None;
    }

    /// A mouse button pressed or released.
    pub fn button(&mut self, button: Button, pressed: bool) {
        if pressed {
            self.drag = Some(button);
        } else if self.drag == Some(button) {
            self.drag = None;
        }
    }

    /// The cursor moved to `(x, y)` window pixels: drags turn the camera.
    pub fn cursor(&mut self, x: f64, y: f64) {
        if let (Some(button), Some((px, py))) = (self.drag, self.cursor) {
            let (dx, dy) = (x - px, y - py);
            match (self.mode, button) {
                (Mode::Orbit, Button::Left) => self.orbit(dx, dy),
                (Mode::Fly, Button::Right) => self.look(dx, dy),
                _ => {}
            }
        }
        self.cursor = Some((x, y));
    }

    /// The cursor left the window: the next move starts a fresh drag delta.
    pub fn cursor_left(&mut self) {
        self.cursor = None;
    }

    /// Wheel by `lines` notches (positive: towards the centre). Orbit mode only.
    pub fn wheel(&mut self, lines: f64) {
        if self.mode != Mode::Orbit || lines == 0.0 || !lines.is_finite() {
            return;
        }
        let offset = self.pose.position - self.centre;
        let distance = offset.length();
        let target = (distance * (-lines * ZOOM_PER_LINE).exp())
            .clamp(MIN_DISTANCE * self.edge, MAX_DISTANCE * self.edge);
        if let Some(dir) = offset.try_normalize() {
            self.look_from(self.centre + dir * target, self.centre);
        }
    }

    /// Advances held fly movement by `dt` seconds.
    pub fn advance(&mut self, dt: f64) {
        if self.mode != Mode::Fly || !(dt > 0.0) || !dt.is_finite() {
            return;
        }
        let axis = |plus: Move, minus: Move| {
            f64::from(u8::from(self.held[plus.index()]))
                - f64::from(u8::from(self.held[minus.index()]))
        };
        let v = self.pose.forward * axis(Move::Forward, Move::Back)
            + self.pose.right() * axis(Move::Right, Move::Left)
            + WORLD_UP * axis(Move::Up, Move::Down);
        if let Some(dir) = v.try_normalize() {
            let position = self.pose.position + dir * (FLY_SPEED * self.edge * dt);
            self.look_from(position, position + self.pose.forward);
        }
    }

    /// Whether any movement key is held.
    pub fn moving(&self) -> bool {
        Move::ALL.iter().any(|m| self.held[m.index()])
    }

    fn orbit(&mut self, dx: f64, dy: f64) {
        let offset = self.pose.position - self.centre;
        let distance = offset.length();
        if !(distance > 0.0) {
            return;
        }
        let (azimuth, elevation) = angles(offset / distance);
        let azimuth = azimuth - dx * ROTATE_PER_PIXEL;
        let elevation = (elevation + dy * ROTATE_PER_PIXEL).clamp(-MAX_PITCH, MAX_PITCH);
        self.look_from(
            self.centre + spherical(azimuth, elevation) * distance,
            self.centre,
        );
    }

    fn look(&mut self, dx: f64, dy: f64) {
        let (yaw, pitch) = angles(self.pose.forward);
        let yaw = yaw - dx * ROTATE_PER_PIXEL;
        let pitch = (pitch - dy * ROTATE_PER_PIXEL).clamp(-MAX_PITCH, MAX_PITCH);
        let p = self.pose.position;
        self.look_from(p, p + spherical(yaw, pitch));
    }

    /// Moves the pose to look from `position` at `target`; a degenerate pose is ignored.
    fn look_from(&mut self, position: DVec3, target: DVec3) {
        if let Ok(c) = Camera::look_at(position, target, WORLD_UP, self.pose.fov_y, 1, 1)
            && c != self.pose
        {
            self.pose = c;
            self.moved = true;
        }
    }
}

/// Azimuth about +Z from +X and elevation above the XY plane of a unit vector.
fn angles(dir: DVec3) -> (f64, f64) {
    (dir.y.atan2(dir.x), dir.z.clamp(-1.0, 1.0).asin())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame() -> SceneFrame {
        SceneFrame {
            origin: [10.0, -4.0, 2.0],
            edge: 8.0,
            max_depth: 10,
        }
    }

    fn centre() -> DVec3 {
        DVec3::from_array(frame().centre())
    }

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() <= 1e-9 * (1.0 + a.abs().max(b.abs()))
    }

    #[test]
    fn starts_at_the_static_path_camera_bit_for_bit() {
        for seed in [0, 1, 7, 12345] {
            let c = Controls::new(&frame(), seed);
            assert_eq!(c.mode(), Mode::Orbit);
            assert!(!c.moved());
            for (w, h) in [(256, 192), (512, 512), (1, 1)] {
                assert_eq!(
                    c.camera(w, h),
                    CameraPath::Static.camera(0, &frame(), seed, w, h)
                );
            }
        }
        let c = Controls::new(&frame(), 1);
        assert_eq!(c.camera(0, 99_999).width, 1);
        assert_eq!(c.camera(0, 99_999).height, MAX_FRAME_SIDE);
    }

    #[test]
    fn left_drag_orbits_about_the_centre_at_constant_distance() {
        let mut c = Controls::new(&frame(), 3);
        let start = c.camera(64, 64);
        let d0 = (start.position - centre()).length();
        c.cursor(100.0, 100.0);
        // Moving without a button does nothing.
        c.cursor(140.0, 90.0);
        assert_eq!(c.camera(64, 64), start);
        c.button(Button::Left, true);
        c.cursor(180.0, 80.0);
        c.button(Button::Left, false);
        c.cursor(300.0, 300.0);
        let moved = c.camera(64, 64);
        assert!(c.moved());
        assert!((moved.position - start.position).length() > 0.1);
        assert!(close((moved.position - centre()).length(), d0));
        let to_centre = (centre() - moved.position).normalize();
        assert!(moved.forward.dot(to_centre) > 1.0 - 1e-12);
        // 40 px right turned the azimuth by 40 · ROTATE_PER_PIXEL (leftwards), 10 px up lowered
        // the elevation by 10 · ROTATE_PER_PIXEL.
        let (a0, e0) = angles((start.position - centre()).normalize());
        let (a1, e1) = angles((moved.position - centre()).normalize());
        assert!(close(a0 - a1, 40.0 * ROTATE_PER_PIXEL), "{a0} {a1}");
        assert!(close(e0 - e1, 10.0 * ROTATE_PER_PIXEL), "{e0} {e1}");
    }

    #[test]
    fn orbit_elevation_stops_short_of_the_pole() {
        let mut c = Controls::new(&frame(), 5);
        c.cursor(0.0, 0.0);
        c.button(Button::Left, true);
        c.cursor(0.0, 1e6);
        let cam = c.camera(8, 8);
        let (_, e) = angles((cam.position - centre()).normalize());
        assert!(close(e, MAX_PITCH), "{e}");
        assert!(cam.up.is_finite() && close(cam.up.length(), 1.0));
    }

    #[test]
    fn wheel_zooms_in_log_distance_within_limits() {
        let mut c = Controls::new(&frame(), 2);
        let d = |c: &Controls| (c.camera(4, 4).position - centre()).length();
        let d0 = d(&c);
        c.wheel(1.0);
        assert!(close(d(&c), d0 * (-ZOOM_PER_LINE).exp()));
        c.wheel(2.0);
        c.wheel(-3.0);
        assert!(close(d(&c), d0));
        c.wheel(1e4);
        assert!(close(d(&c), MIN_DISTANCE * frame().edge));
        c.wheel(-1e4);
        assert!(close(d(&c), MAX_DISTANCE * frame().edge));
        c.wheel(f64::NAN);
        assert!(close(d(&c), MAX_DISTANCE * frame().edge));
    }

    #[test]
    fn fly_moves_with_held_keys_and_right_drag_looks() {
        let mut c = Controls::new(&frame(), 9);
        // Keys do nothing in orbit mode.
        c.key(Move::Forward, true);
        c.advance(1.0);
        assert!(!c.moved());
        c.toggle_mode();
        assert_eq!(c.mode(), Mode::Fly);
        let start = c.camera(16, 16);
        c.advance(0.5);
        let after = c.camera(16, 16);
        let step = after.position - start.position;
        assert!(close(step.length(), FLY_SPEED * frame().edge * 0.5));
        assert!(step.normalize().dot(start.forward) > 1.0 - 1e-12);
        assert!(after.forward.dot(start.forward) > 1.0 - 1e-12);
        // Forward and right together: diagonal at the same speed.
        c.key(Move::Right, true);
        c.advance(1.0);
        let diag = c.camera(16, 16).position - after.position;
        assert!(close(diag.length(), FLY_SPEED * frame().edge));
        assert!(close(diag.dot(after.right()), diag.dot(after.forward)));
        c.release_all();
        assert!(!c.moving());
        let still = c.camera(16, 16);
        c.advance(1.0);
        assert_eq!(c.camera(16, 16), still);
        // Up goes along world up.
        c.key(Move::Up, true);
        c.advance(1.0);
        c.key(Move::Up, false);
        let up = c.camera(16, 16).position - still.position;
        assert!(close(up.z, FLY_SPEED * frame().edge) && close(up.x, 0.0));
        // Right-drag turns the view, not the position; left-drag does nothing in fly mode.
        let before = c.camera(16, 16);
        c.cursor(0.0, 0.0);
        c.button(Button::Left, true);
        c.cursor(50.0, 0.0);
        c.button(Button::Left, false);
        assert_eq!(c.camera(16, 16), before);
        c.button(Button::Right, true);
        c.cursor(100.0, 10.0);
        let turned = c.camera(16, 16);
        assert_eq!(turned.position, before.position);
        let (y0, _) = angles(before.forward);
        let (y1, _) = angles(turned.forward);
        assert!(close(y0 - y1, 50.0 * ROTATE_PER_PIXEL), "{y0} {y1}");
    }

    #[test]
    fn back_to_orbit_faces_the_centre() {
        let mut c = Controls::new(&frame(), 4);
        c.toggle_mode();
        c.cursor(0.0, 0.0);
        c.button(Button::Right, true);
        c.cursor(200.0, 0.0);
        assert!(
            c.camera(8, 8)
                .forward
                .dot((centre() - c.camera(8, 8).position).normalize())
                < 0.99
        );
        c.toggle_mode();
        assert_eq!(c.mode(), Mode::Orbit);
        let cam = c.camera(8, 8);
        assert!(cam.forward.dot((centre() - cam.position).normalize()) > 1.0 - 1e-12);
    }
}
