//! Scene management routes: `POST /v1/scenes` (import server-side files under the import root),
//! `GET /v1/imports`, `GET /v1/imports/{id}`, `DELETE /v1/scenes/{name}`. The work is done by
//! [`LiveImports`]; this module maps its answers to HTTP.

use axum::extract::rejection::{JsonRejection, PathRejection};
use axum::extract::{Json, Path, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};

use super::{ApiError, Shared, accepted, scene_name};
use crate::live_import::{ImportRequest, LiveImportError, LiveImports};

impl From<LiveImportError> for ApiError {
    fn from(e: LiveImportError) -> Self {
        let status = match &e {
            LiveImportError::Disabled
            | LiveImportError::Traversal { .. }
            | LiveImportError::OutsideRoot { .. } => StatusCode::FORBIDDEN,
            LiveImportError::NotFound { .. } | LiveImportError::BadRequest(_) => {
                StatusCode::BAD_REQUEST
            }
            LiveImportError::SceneExists(_) => StatusCode::CONFLICT,
            LiveImportError::Pool(_) => return ApiError::internal(e),
        };
        ApiError::new(status, e.to_string())
    }
}

fn manager(app: &Shared) -> Result<&LiveImports, ApiError> {
    app.imports
        .as_ref()
        .ok_or_else(|| ApiError::from(LiveImportError::Disabled))
}

/// `POST /v1/scenes`: `202` with `{"id", "status"}`; the import runs in the background.
pub(super) async fn submit(
    State(app): State<Shared>,
    body: Result<Json<ImportRequest>, JsonRejection>,
) -> Result<Response, ApiError> {
    let Json(request) = body.map_err(|e| ApiError::new(StatusCode::BAD_REQUEST, e.body_text()))?;
    let imports = manager(&app)?.clone();
    // Path resolution and the pool lookup touch the disk.
    let id = tokio::task::spawn_blocking(move || imports.submit(request))
        .await
        .map_err(|e| ApiError::internal(format!("import submit task: {e}")))??;
    Ok(accepted(id, format!("/v1/imports/{id}")))
}

/// `GET /v1/imports`: every kept import.
pub(super) async fn list(State(app): State<Shared>) -> Result<Response, ApiError> {
    Ok(Json(manager(&app)?.list()).into_response())
}

/// `GET /v1/imports/{id}`: one import's phase, counts, error or figures.
pub(super) async fn status(
    State(app): State<Shared>,
    id: Result<Path<u64>, PathRejection>,
) -> Result<Response, ApiError> {
    let Path(id) = id.map_err(|e| ApiError::new(StatusCode::NOT_FOUND, e.body_text()))?;
    match manager(&app)?.status(id) {
        Some(s) => Ok(Json(s).into_response()),
        None => Err(ApiError::new(
            StatusCode::NOT_FOUND,
            "no import with that id",
        )),
    }
}

/// `DELETE /v1/scenes/{name}`: unpublished at once; sessions reading it finish on it.
pub(super) async fn remove(
    State(app): State<Shared>,
    name: Result<Path<String>, PathRejection>,
) -> Result<Response, ApiError> {
    let name = scene_name(name)?;
    let imports = manager(&app)?.clone();
    let removed = name.clone();
    tokio::task::spawn_blocking(move || imports.remove_scene(&removed))
        .await
        .map_err(|e| ApiError::internal(format!("scene removal task: {e}")))??;
    Ok(Json(serde_json::json!({ "removed": name })).into_response())
}
