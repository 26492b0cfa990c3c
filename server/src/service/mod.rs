//! The treelet service (DESIGN §6).
//!
//! * [`schedule`] is its I/O-free core, in the style of quinn-proto: a deterministic state machine
//!   that is told what happened (`handle_*`: a request list arrived, a treelet was sent, delivered
//!   or cancelled) and asked what to do next (`poll_transmit`), with time passed in. It decides,
//!   for every connection, which treelets to send in which order, how many may be in flight, and
//!   which connection goes next; it is unit- and property-tested without sockets.
//! * The networked parts (QUIC with quinn, the control stream, treelet streams, the admin API)
//!   drive it and are built on top.
pub mod schedule;
pub mod state;
