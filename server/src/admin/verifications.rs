//! Scene check routes: `POST /v1/scenes/{name}/verify`, `GET /v1/verifications`,
//! `GET /v1/verifications/{id}`, `DELETE /v1/verifications/{id}`. The work is done by
//! [`crate::live_verify::Verifications`]; this module maps its answers to HTTP.

use axum::extract::rejection::PathRejection;
use axum::extract::{Json, Path, State};
use axum::response::{IntoResponse, Response};

use super::{ApiError, Shared, accepted, id_of, job_answer, manager, scene_name};

/// `POST /v1/scenes/{name}/verify`: `202` with `{"id", "status"}`; the check runs in the
/// background on the generation published now.
pub(super) async fn submit(
    State(app): State<Shared>,
    name: Result<Path<String>, PathRejection>,
) -> Result<Response, ApiError> {
    let name = scene_name(name)?;
    let manager = manager(&app)?.clone();
    // Opening the scene's trees touches the disk.
    let id = tokio::task::spawn_blocking(move || manager.verifications().submit(&name))
        .await
        .map_err(|e| ApiError::internal(format!("verification submit task: {e}")))??;
    Ok(accepted(id, format!("/v1/verifications/{id}")))
}

/// `GET /v1/verifications`: every kept check.
pub(super) async fn list(State(app): State<Shared>) -> Result<Response, ApiError> {
    Ok(Json(manager(&app)?.verifications().list()).into_response())
}

/// `GET /v1/verifications/{id}`: one check's phase, counts, error or report.
pub(super) async fn status(
    State(app): State<Shared>,
    id: Result<Path<u64>, PathRejection>,
) -> Result<Response, ApiError> {
    let id = id_of(id)?;
    job_answer(manager(&app)?.verifications().status(id), "verification")
}

/// `DELETE /v1/verifications/{id}`: stops a queued or running check after the batch in hand;
/// answers its status (`cancelled` once the worker has stopped it).
pub(super) async fn cancel(
    State(app): State<Shared>,
    id: Result<Path<u64>, PathRejection>,
) -> Result<Response, ApiError> {
    let id = id_of(id)?;
    job_answer(manager(&app)?.verifications().cancel(id), "verification")
}
