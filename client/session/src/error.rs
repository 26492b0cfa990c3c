//! Why a run could not start or go on.

use arbor_client_core::backend::BackendError;
use arbor_client_core::cycle::CoreError;
use arbor_client_core::slots::SlotError;
use arbor_client_net::ClientError;
use thiserror::Error;

/// Why a session or a run could not start or go on.
#[derive(Debug, Error)]
pub enum RunError {
    /// The connection could not be set up (bad URL, certificate, configuration).
    #[error("client: {0}")]
    Client(#[from] ClientError),
    /// The client core refused its configuration or the root treelet.
    #[error(transparent)]
    Core(#[from] CoreError),
    /// No `SceneInfo` or no root treelet within the connect timeout.
    #[error("{0}")]
    Timeout(String),
    /// The server refused the client for good (token, scene, certificate).
    #[error("server refused the connection: {0}")]
    Refused(String),
    /// A parameter of the run is out of range.
    #[error("invalid parameter: {0}")]
    Invalid(String),
    /// The reference image does not fit the run.
    #[error("reference image: {0}")]
    Reference(String),
    /// The backend could not run a pass (a lost or faulted GPU device).
    #[error(transparent)]
    Backend(#[from] BackendError),
}

impl From<SlotError> for RunError {
    fn from(e: SlotError) -> Self {
        RunError::Core(CoreError::Slots(e))
    }
}
