//! Whole-system tests of Arbor; shared test support lives here.

pub mod corpus;
