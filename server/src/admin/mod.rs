//! The admin HTTP API of the server daemon (docs/design.md §6): health, readiness, Prometheus metrics,
//! the pool's scenes, live sessions and a small HTML status page, on its own listener (loopback by
//! default), served with axum.
//!
//! | route                   | auth   | answer                                                   |
//! |-------------------------|--------|----------------------------------------------------------|
//! | `GET /healthz`          | none   | `200 ok` while the process runs                          |
//! | `GET /readyz`           | token  | `200 ready`, or `503 not ready`                          |
//! | `GET /metrics`          | token  | Prometheus text 0.0.4: service counters + pool gauges    |
//! | `GET /v1/scenes`        | token  | JSON array of scene figures                              |
//! | `GET /v1/scenes/{name}` | token  | one scene, `404` JSON error when unknown                 |
//! | `GET /v1/sessions`      | token  | JSON array of live connections and their counters        |
//! | `GET /v1/server`        | token  | fingerprint, readiness, shutting down, uptime, version   |
//! | `GET /v1/paths`         | token  | JSON array of remembered client paths (path memory)      |
//! | `DELETE /v1/paths`      | token  | forgets them (after a network change): `{"forgotten": n}` |
//! | `POST /v1/scenes`       | token  | JSON import request: `202` + import id (see below)       |
//! | `DELETE /v1/scenes/{name}` | token | removes a scene; its sessions finish on it            |
//! | `GET /v1/imports`       | token  | JSON array of imports (queued, running, last finished)   |
//! | `GET /v1/imports/{id}`  | token  | one import: phase, done/total, error or figures          |
//! | `POST /v1/scenes/{name}/verify` | token | checks the scene while serving: `202` + check id |
//! | `GET /v1/verifications` | token  | JSON array of checks (queued, running, last finished)    |
//! | `GET /v1/verifications/{id}` | token | one check: phase, treelets checked, error or report |
//! | `DELETE /v1/verifications/{id}` | token | cancels a check (after the batch in hand)        |
//! | `POST /v1/copies`       | token  | copies the served pool under the copy root: `202` + copy id |
//! | `GET /v1/copies`        | token  | JSON array of copies (queued, running, last finished)    |
//! | `GET /v1/copies/{id}`   | token  | one copy: phase, bytes copied, error or summary          |
//! | `DELETE /v1/copies/{id}` | token | cancels a copy (after the pack in hand; nothing is left) |
//! | `GET /v1/background-reads` | token | the checks' and copies' read rate, bytes read, seconds waited |
//! | `PUT /v1/background-reads` | token | `{"read_bytes_per_second": N, "20MB" or null}`: sets the rate |
//! | `GET /`                 | token  | HTML status page; without credentials, `303` to `/login` |
//! | `GET /login`            | none   | HTML form asking for the token                           |
//! | `POST /login`           | none   | form field `token`: sets the `arbor_admin` cookie, `303` |
//! | `POST /logout`          | none   | clears the cookie, `303` to `/login`                     |
//!
//! Credentials are `Authorization: Bearer <token>` or the `arbor_admin` cookie set by `/login`
//! (HttpOnly, SameSite=Strict); both are compared in constant time against the configured token
//! (see `auth.rs`). Unauthenticated API requests get `401` with `WWW-Authenticate: Bearer` and a
//! JSON error; every error is JSON `{"error": "..."}`; unknown routes are `404`. The token is never
//! logged, and [`AdminContext`]'s `Debug` redacts it.
//!
//! Scene management ([`router_with_imports`], `imports.rs`, [`crate::live_import`]): `POST
//! /v1/scenes` takes `{"scene", "inputs": [paths under the import root], "replace", "depth",
//! "treelet_bytes", "iso", "format", "memory_budget_mib", "allow_mixed_crs"}`; `403` when imports
//! are disabled or a path leaves the import root (`..`, symlinks), `400` for a missing file or a
//! bad parameter, `409` for a taken name. Parse errors come later, in the import's status.
//!
//! Scene checks (`verifications.rs`, [`crate::live_verify`]): `POST /v1/scenes/{name}/verify`
//! checks the generation published now with `arbor-server verify`'s invariants, `404` for an
//! unknown scene; asking again while that generation's check is queued or running answers the
//! same id. A check's `phase` is `queued`, `running`, `ok`, `problems` (the `report` lists them),
//! `failed` (the pool could not be read: `error`) or `cancelled`.
//!
//! Pool copies (`copies.rs`, [`crate::live_copy`]): `POST /v1/copies` takes `{"to": NAME,
//! "scenes": [names]}` (no scenes: every published scene) and copies them, as published now,
//! into the new directory `NAME` under the daemon's `--copy-root`; `403` when copies are
//! disabled, `400` for a name that is not a plain directory name (or is named as scheduled
//! copies are, `scheduled-<UTC time>`, which `--copy-keep` removes), `409` when the destination
//! exists or another copy writes it, `404` for an unknown scene. A copy's `phase` is `queued`,
//! `running`, `done` (`report`: packs and bytes per scene, carried files, seconds), `failed`
//! (`error`; nothing left at the destination) or `cancelled`.
//!
//! Background reads (`background.rs`, [`crate::pace`]): checks and copies read the pool at most
//! at the daemon's `--background-read-rate` together; `PUT /v1/background-reads` changes it
//! while they run (`400` for a rate outside 1 kB/s to 1 TB/s or unreadable text).

mod auth;
mod background;
mod copies;
pub mod https;
mod imports;
mod metrics;
mod page;
mod verifications;
mod views;

use std::fmt;
use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::Router;
use axum::extract::rejection::{FormRejection, PathRejection};
use axum::extract::{Form, Path, Request, State};
use axum::http::{HeaderValue, Method, StatusCode, header};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use serde::Deserialize;

use crate::live_import::LiveImports;
use crate::pool::{Pool, PoolError};
use crate::service::state::ServiceState;

pub use auth::{AdminCredentials, COOKIE};

/// What the admin API reads.
#[derive(Clone, Debug)]
pub struct AdminContext {
    pub state: Arc<ServiceState>,
    pub pool: Pool,
    /// The bearer tokens: the admin token of every route but `/healthz` (and the login form),
    /// and the probe token of `/readyz`.
    pub credentials: Arc<AdminCredentials>,
}

/// The router's shared state.
#[derive(Debug)]
struct App {
    state: Arc<ServiceState>,
    pool: Pool,
    credentials: Arc<AdminCredentials>,
    /// When the router was made: the service makes it at start, so this is the service's uptime.
    started: Instant,
    /// `Content-Security-Policy` of the HTML pages (hashes of their inline style and script).
    csp: HeaderValue,
    /// Scene management; `None`: the routes answer `403`.
    imports: Option<LiveImports>,
}

type Shared = Arc<App>;

/// The admin HTTP routes, without scene management (its routes answer `403`).
pub fn router(ctx: AdminContext) -> Router {
    router_with_imports(ctx, None)
}

/// The admin HTTP routes, with scene management by `imports`.
pub fn router_with_imports(ctx: AdminContext, imports: Option<LiveImports>) -> Router {
    let app: Shared = Arc::new(App {
        credentials: ctx.credentials,
        state: ctx.state,
        pool: ctx.pool,
        started: Instant::now(),
        csp: page::content_security_policy(),
        imports,
    });
    let protected = Router::new()
        .route("/", get(index))
        .route("/readyz", get(readyz))
        .route("/metrics", get(prometheus))
        .route("/v1/scenes", get(scenes).post(imports::submit))
        .route("/v1/scenes/{name}", get(scene).delete(imports::remove))
        .route("/v1/imports", get(imports::list))
        .route("/v1/imports/{id}", get(imports::status))
        .route("/v1/scenes/{name}/verify", post(verifications::submit))
        .route("/v1/verifications", get(verifications::list))
        .route(
            "/v1/verifications/{id}",
            get(verifications::status).delete(verifications::cancel),
        )
        .route("/v1/copies", get(copies::list).post(copies::submit))
        .route(
            "/v1/copies/{id}",
            get(copies::status).delete(copies::cancel),
        )
        .route(
            "/v1/background-reads",
            get(background::figures).put(background::set),
        )
        .route("/v1/sessions", get(sessions))
        .route("/v1/paths", get(paths).delete(forget_paths))
        .route("/v1/server", get(server))
        .route_layer(middleware::from_fn_with_state(app.clone(), require_auth));
    Router::new()
        .route("/healthz", get(healthz))
        .route("/login", get(login_form).post(login))
        .route("/logout", post(logout))
        .merge(protected)
        .fallback(not_found)
        .method_not_allowed_fallback(method_not_allowed)
        .layer(middleware::map_response(common_headers))
        .layer(middleware::from_fn(log_request))
        .with_state(app)
}

/// A JSON error `{"error": "..."}` with its status.
#[derive(Debug)]
struct ApiError {
    status: StatusCode,
    message: String,
}

impl ApiError {
    fn new(status: StatusCode, message: impl Into<String>) -> Self {
        Self {
            status,
            message: message.into(),
        }
    }

    fn internal(message: impl fmt::Display) -> Self {
        tracing::error!("admin API: {message}");
        Self::new(StatusCode::INTERNAL_SERVER_ERROR, message.to_string())
    }
}

impl From<PoolError> for ApiError {
    fn from(e: PoolError) -> Self {
        match e {
            PoolError::NoSuchScene(_) => Self::new(StatusCode::NOT_FOUND, e.to_string()),
            e => Self::internal(e),
        }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        json_error(self.status, &self.message)
    }
}

/// A scene name from the route's path; a name no scene can have is `404`, like an unknown one.
fn scene_name(name: Result<Path<String>, PathRejection>) -> Result<String, ApiError> {
    let Path(name) = name.map_err(|e| ApiError::new(StatusCode::BAD_REQUEST, e.body_text()))?;
    if arbor_proto::scene::validate_scene_name(&name).is_err() {
        return Err(PoolError::NoSuchScene(name).into());
    }
    Ok(name)
}

/// The daemon's scene manager, which the routes of background work reach; `403` when this
/// admin API was started without one.
fn manager(app: &Shared) -> Result<&LiveImports, ApiError> {
    app.imports.as_ref().ok_or_else(|| {
        ApiError::new(
            StatusCode::FORBIDDEN,
            "scene management is not mounted on this admin API",
        )
    })
}

/// A background job's id from the route's path; one that is not a number is `404`, like an
/// unknown one.
fn id_of(id: Result<Path<u64>, PathRejection>) -> Result<u64, ApiError> {
    let Path(id) = id.map_err(|e| ApiError::new(StatusCode::NOT_FOUND, e.body_text()))?;
    Ok(id)
}

/// A background job's status as JSON, or `404` saying there is no `what` with that id.
fn job_answer<S: serde::Serialize>(status: Option<S>, what: &str) -> Result<Response, ApiError> {
    let status = status
        .ok_or_else(|| ApiError::new(StatusCode::NOT_FOUND, format!("no {what} with that id")))?;
    Ok(axum::Json(status).into_response())
}

/// `202 Accepted` for background work: `Location` and `{"id", "status"}` name where its status
/// is read.
fn accepted(id: u64, location: String) -> Response {
    (
        StatusCode::ACCEPTED,
        [(header::LOCATION, location.clone())],
        axum::Json(serde_json::json!({ "id": id, "status": location })),
    )
        .into_response()
}

fn json_error(status: StatusCode, message: &str) -> Response {
    (status, axum::Json(serde_json::json!({ "error": message }))).into_response()
}

/// Runs a blocking pool read off the async workers.
async fn with_pool<T: Send + 'static>(
    app: &Shared,
    f: impl FnOnce(&Pool) -> Result<T, PoolError> + Send + 'static,
) -> Result<T, ApiError> {
    let pool = app.pool.clone();
    tokio::task::spawn_blocking(move || f(&pool))
        .await
        .map_err(|e| ApiError::internal(format!("pool reader task: {e}")))?
        .map_err(ApiError::from)
}

/// Admits requests with a valid bearer token or cookie; otherwise `/` goes to the login form and
/// everything else gets `401`.
async fn require_auth(State(app): State<Shared>, req: Request, next: Next) -> Response {
    // The probe token opens readiness and nothing else.
    let tokens = app.credentials.current();
    if req.uri().path() == "/readyz"
        && let Some(probe) = &tokens.probe
        && auth::check(req.headers(), probe) == auth::Credentials::Valid
    {
        return next.run(req).await;
    }
    let presented = auth::check(req.headers(), &tokens.admin);
    if presented == auth::Credentials::Valid {
        return next.run(req).await;
    }
    let path = req.uri().path();
    // A browser (no Authorization header) asking for the status page goes to the login form.
    if path == "/"
        && matches!(*req.method(), Method::GET | Method::HEAD)
        && !req.headers().contains_key(header::AUTHORIZATION)
    {
        return see_other("/login", None);
    }
    let (message, challenge) = match presented {
        auth::Credentials::Invalid => {
            tracing::info!(path, "admin API: rejected a request with a wrong token");
            (
                "invalid credentials",
                r#"Bearer realm="arbor-admin", error="invalid_token""#,
            )
        }
        _ => {
            tracing::debug!(path, "admin API: rejected a request without credentials");
            (
                "authentication required: send Authorization: Bearer <token>",
                r#"Bearer realm="arbor-admin""#,
            )
        }
    };
    let mut r = json_error(StatusCode::UNAUTHORIZED, message);
    r.headers_mut().insert(
        header::WWW_AUTHENTICATE,
        HeaderValue::from_static(challenge),
    );
    r
}

/// Headers every answer carries: nothing here may be cached or sniffed or framed.
async fn common_headers(mut r: Response) -> Response {
    let h = r.headers_mut();
    h.entry(header::CACHE_CONTROL)
        .or_insert(HeaderValue::from_static("no-store"));
    h.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    h.insert(header::X_FRAME_OPTIONS, HeaderValue::from_static("DENY"));
    h.insert(
        header::REFERRER_POLICY,
        HeaderValue::from_static("no-referrer"),
    );
    r
}

/// One debug line per request: method, path (never headers, so never the token), status, time.
async fn log_request(req: Request, next: Next) -> Response {
    let method = req.method().clone();
    let path = req.uri().path().to_owned();
    let t = Instant::now();
    let r = next.run(req).await;
    tracing::debug!(
        %method,
        path,
        status = r.status().as_u16(),
        micros = t.elapsed().as_micros() as u64,
        "admin request"
    );
    r
}

fn see_other(location: &'static str, cookie: Option<String>) -> Response {
    let mut r = StatusCode::SEE_OTHER.into_response();
    r.headers_mut()
        .insert(header::LOCATION, HeaderValue::from_static(location));
    if let Some(c) = cookie {
        match HeaderValue::from_str(&c) {
            Ok(v) => {
                r.headers_mut().insert(header::SET_COOKIE, v);
            }
            Err(_) => return ApiError::internal("cookie not a valid header").into_response(),
        }
    }
    r
}

fn text(status: StatusCode, body: &'static str) -> Response {
    (
        status,
        [(
            header::CONTENT_TYPE,
            HeaderValue::from_static("text/plain; charset=utf-8"),
        )],
        body,
    )
        .into_response()
}

fn html(app: &App, status: StatusCode, body: String) -> Response {
    (
        status,
        [
            (
                header::CONTENT_TYPE,
                HeaderValue::from_static("text/html; charset=utf-8"),
            ),
            (header::CONTENT_SECURITY_POLICY, app.csp.clone()),
        ],
        body,
    )
        .into_response()
}

async fn healthz() -> Response {
    text(StatusCode::OK, "ok")
}

async fn readyz(State(app): State<Shared>) -> Response {
    if app.state.is_ready() {
        text(StatusCode::OK, "ready")
    } else {
        text(StatusCode::SERVICE_UNAVAILABLE, "not ready")
    }
}

async fn prometheus(State(app): State<Shared>) -> Response {
    // A pool that cannot be read must not hide the service's own metrics: the pool's gauges are
    // left without samples and `arbor_pool_readable` says 0.
    let pool = with_pool(&app, metrics::PoolFigures::read).await;
    if let Err(e) = &pool {
        tracing::warn!("admin /metrics: pool figures unavailable: {}", e.message);
    }
    let checks = match (&app.imports, &pool) {
        (Some(imports), Ok(pool)) => Some(imports.verifications().figures_of(&pool.generations)),
        _ => None,
    };
    let copies = app.imports.as_ref().map(|i| i.copies().figures());
    let background = app.imports.as_ref().map(|i| i.background_reads().figures());
    let body = metrics::render(
        &app.state,
        app.started.elapsed(),
        app.pool.read_times(),
        pool.ok().as_ref(),
        checks.as_ref(),
        copies.as_ref(),
        background.as_ref(),
    );
    (
        StatusCode::OK,
        [(
            header::CONTENT_TYPE,
            HeaderValue::from_static(metrics::CONTENT_TYPE),
        )],
        body,
    )
        .into_response()
}

async fn scenes(State(app): State<Shared>) -> Result<Response, ApiError> {
    let scenes = with_pool(&app, Pool::scenes).await?;
    let views: Vec<_> = scenes.iter().map(views::SceneView::new).collect();
    Ok(axum::Json(views).into_response())
}

async fn scene(
    State(app): State<Shared>,
    name: Result<Path<String>, PathRejection>,
) -> Result<Response, ApiError> {
    let Path(name) = name.map_err(|e| ApiError::new(StatusCode::BAD_REQUEST, e.body_text()))?;
    if arbor_proto::scene::validate_scene_name(&name).is_err() {
        return Err(ApiError::new(
            StatusCode::NOT_FOUND,
            "no scene of that name (not a valid scene name)",
        ));
    }
    let d = with_pool(&app, move |p| p.scene(&name).map(|s| s.description)).await?;
    Ok(axum::Json(views::SceneView::new(&d)).into_response())
}

async fn sessions(State(app): State<Shared>) -> Response {
    axum::Json(app.state.sessions()).into_response()
}

async fn paths(State(app): State<Shared>) -> Response {
    let views = app.state.paths().snapshot(Instant::now());
    axum::Json(views).into_response()
}

async fn forget_paths(State(app): State<Shared>) -> Response {
    let forgotten = app.state.paths().clear();
    tracing::info!(forgotten, "path memory cleared through the admin API");
    axum::Json(serde_json::json!({ "forgotten": forgotten })).into_response()
}

async fn server(State(app): State<Shared>) -> Response {
    axum::Json(views::ServerView::new(&app.state, app.started.elapsed())).into_response()
}

async fn index(State(app): State<Shared>) -> Result<Response, ApiError> {
    let pool = with_pool(&app, metrics::PoolFigures::read).await?;
    let imports = app
        .imports
        .as_ref()
        .map(LiveImports::list)
        .unwrap_or_default();
    let checks = app
        .imports
        .as_ref()
        .map(|i| i.verifications().list())
        .unwrap_or_default();
    let copies = app
        .imports
        .as_ref()
        .map(|i| i.copies().list())
        .unwrap_or_default();
    let jobs = page::Jobs {
        imports: &imports,
        checks: &checks,
        copies: &copies,
        background: app.imports.as_ref().map(|i| i.background_reads().figures()),
        scheduled_checks: app
            .imports
            .as_ref()
            .and_then(|i| i.verifications().scheduled()),
        scheduled_copies: app.imports.as_ref().and_then(|i| {
            let f = i.copies().figures();
            f.scheduled.map(|s| (s, f.skipped))
        }),
    };
    let body = page::status_page(&app.state, app.started.elapsed(), &pool, &jobs);
    Ok(html(&app, StatusCode::OK, body))
}

async fn login_form(State(app): State<Shared>) -> Response {
    html(&app, StatusCode::OK, page::login_page(None))
}

#[derive(Deserialize)]
struct LoginForm {
    token: String,
}

/// Checks the token of the form; a right one sets the cookie and goes to the status page.
async fn login(
    State(app): State<Shared>,
    form: Result<Form<LoginForm>, FormRejection>,
) -> Response {
    let Ok(Form(form)) = form else {
        return html(
            &app,
            StatusCode::BAD_REQUEST,
            page::login_page(Some("The form must carry a token field.")),
        );
    };
    if app
        .credentials
        .current()
        .admin
        .matches(form.token.as_bytes())
    {
        tracing::info!("admin API: browser login");
        see_other("/", Some(auth::set_cookie(&form.token)))
    } else {
        tracing::info!("admin API: failed browser login");
        // Slows guessing through the form a little; the bearer path is as slow as the network.
        tokio::time::sleep(Duration::from_millis(200)).await;
        html(
            &app,
            StatusCode::UNAUTHORIZED,
            page::login_page(Some("Wrong token.")),
        )
    }
}

async fn logout() -> Response {
    see_other("/login", Some(auth::clear_cookie()))
}

async fn not_found() -> Response {
    json_error(StatusCode::NOT_FOUND, "no such route")
}

async fn method_not_allowed() -> Response {
    json_error(
        StatusCode::METHOD_NOT_ALLOWED,
        "method not allowed on this route",
    )
}
