//! Whole-system tests of Arbor against the real scans in `../shared/data`; shared support lives
//! here: the bad-input corpus ([`corpus`]) and scene building plus brute-force references
//! ([`support`]).

#![forbid(unsafe_code)]

pub mod corpus;
pub mod link;
pub mod streaming;
pub mod support;
