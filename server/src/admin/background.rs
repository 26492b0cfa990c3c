//! The pace of background reads: `GET /v1/background-reads` answers the rate, the bytes the
//! checks and copies read and the seconds they waited; `PUT /v1/background-reads` with
//! `{"read_bytes_per_second": N | "20MB" | "off" | null}` sets the rate while they run. The
//! pace itself is [`crate::pace::ReadPace`]; this module maps it to HTTP.

use axum::extract::rejection::JsonRejection;
use axum::extract::{Json, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use serde::Deserialize;

use super::{ApiError, Shared, manager};
use crate::pace::{self, PaceError};

/// A rate as a request writes it: bytes per second, or text as `--background-read-rate`
/// reads it.
#[derive(Debug, Deserialize)]
#[serde(untagged)]
enum RateValue {
    Bytes(u64),
    Text(String),
}

/// `PUT /v1/background-reads`'s body.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct PaceRequest {
    /// `null`: no limit.
    read_bytes_per_second: Option<RateValue>,
}

impl From<PaceError> for ApiError {
    fn from(e: PaceError) -> Self {
        ApiError::new(StatusCode::BAD_REQUEST, e.to_string())
    }
}

/// `GET /v1/background-reads`.
pub(super) async fn figures(State(app): State<Shared>) -> Result<Response, ApiError> {
    Ok(Json(manager(&app)?.background_reads().figures()).into_response())
}

/// `PUT /v1/background-reads`: the new rate takes effect at once (a read waiting under the
/// old one stops waiting); answers as `GET` does.
pub(super) async fn set(
    State(app): State<Shared>,
    body: Result<Json<PaceRequest>, JsonRejection>,
) -> Result<Response, ApiError> {
    let Json(request) = body.map_err(|e| ApiError::new(StatusCode::BAD_REQUEST, e.body_text()))?;
    let rate = match request.read_bytes_per_second {
        None => None,
        Some(RateValue::Bytes(n)) => pace::validate(Some(n))?,
        Some(RateValue::Text(t)) => pace::parse_rate(&t)?,
    };
    let reads = manager(&app)?.background_reads();
    reads.set_rate(rate);
    Ok(Json(reads.figures()).into_response())
}
