//! Pool copy routes: `POST /v1/copies`, `GET /v1/copies`, `GET /v1/copies/{id}`,
//! `DELETE /v1/copies/{id}`. The work is done by [`crate::live_copy::Copies`]; this module maps
//! its answers to HTTP.

use axum::extract::rejection::{JsonRejection, PathRejection};
use axum::extract::{Json, Path, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};

use super::{ApiError, Shared, accepted, id_of, job_answer, manager};
use crate::live_copy::{CopyRequest, LiveCopyError};

impl From<LiveCopyError> for ApiError {
    fn from(e: LiveCopyError) -> Self {
        match e {
            LiveCopyError::Pool(e) => e.into(),
            e @ LiveCopyError::Disabled => ApiError::new(StatusCode::FORBIDDEN, e.to_string()),
            e @ (LiveCopyError::BadName(_) | LiveCopyError::Reserved(_)) => {
                ApiError::new(StatusCode::BAD_REQUEST, e.to_string())
            }
            e @ LiveCopyError::DestinationTaken(..) => {
                ApiError::new(StatusCode::CONFLICT, e.to_string())
            }
        }
    }
}

/// `POST /v1/copies` with `{"to", "scenes"}`: `202` with `{"id", "status"}`; the copy runs in
/// the background on the generations published now.
pub(super) async fn submit(
    State(app): State<Shared>,
    body: Result<Json<CopyRequest>, JsonRejection>,
) -> Result<Response, ApiError> {
    let Json(request) = body.map_err(|e| ApiError::new(StatusCode::BAD_REQUEST, e.body_text()))?;
    let manager = manager(&app)?.clone();
    // Opening the scenes' trees touches the disk.
    let id = tokio::task::spawn_blocking(move || manager.copies().submit(&request))
        .await
        .map_err(|e| ApiError::internal(format!("copy submit task: {e}")))??;
    Ok(accepted(id, format!("/v1/copies/{id}")))
}

/// `GET /v1/copies`: every kept copy.
pub(super) async fn list(State(app): State<Shared>) -> Result<Response, ApiError> {
    Ok(Json(manager(&app)?.copies().list()).into_response())
}

/// `GET /v1/copies/{id}`: one copy's phase, bytes, error or summary.
pub(super) async fn status(
    State(app): State<Shared>,
    id: Result<Path<u64>, PathRejection>,
) -> Result<Response, ApiError> {
    let id = id_of(id)?;
    job_answer(manager(&app)?.copies().status(id), "copy")
}

/// `DELETE /v1/copies/{id}`: stops a queued or running copy after the pack in hand, which then
/// removes what it wrote; answers its status (`cancelled` once the worker has stopped it).
pub(super) async fn cancel(
    State(app): State<Shared>,
    id: Result<Path<u64>, PathRejection>,
) -> Result<Response, ApiError> {
    let id = id_of(id)?;
    job_answer(manager(&app)?.copies().cancel(id), "copy")
}
