//! PLACEHOLDER being replaced by the admin-API work: the contract is `router(AdminContext)`.

use std::sync::Arc;

use crate::pool::Pool;
use crate::service::state::ServiceState;

/// What the admin API reads.
#[derive(Debug, Clone)]
pub struct AdminContext {
    pub state: Arc<ServiceState>,
    pub pool: Pool,
    /// Bearer token required on every route but `/healthz`.
    pub token: String,
}

/// The admin HTTP routes.
pub fn router(_ctx: AdminContext) -> axum::Router {
    axum::Router::new()
}
