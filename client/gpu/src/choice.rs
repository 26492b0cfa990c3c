//! Which backend a run uses: the GPU when asked for or when `auto` finds a hardware adapter,
//! else the CPU twins of `arbor-client-core`, saying why.
//!
//! A software adapter (Mesa's lavapipe, what wgpu finds on a machine without a GPU) runs the
//! passes on the machine's own cores, and there the CPU twins are faster: on two cores,
//! lion-1k served over loopback converged in 0.36 s at 256² and 2.55 s at 1024² on the twins,
//! against 1.30 s and 15.5 s on lavapipe (its 1024² render takes about 0.7 s a frame, the twins'
//! 0.4 s, and the twins re-render only what changed). So `auto` takes the twins then, and says
//! so; `gpu` still runs on it.

use std::sync::Arc;

use arbor_client_core::backend::{Backend, CpuBackend};

use crate::{FeedbackMode, GpuBackend, GpuContext, GpuError};

/// Which backend a run asks for.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum BackendChoice {
    /// The GPU when a hardware adapter exists, else the CPU twins — saying so (a software
    /// adapter such as lavapipe is slower than the twins on the same cores).
    #[default]
    Auto,
    /// The GPU or an error.
    Gpu,
    /// The CPU twins.
    Cpu,
}

impl BackendChoice {
    /// Parses `auto`, `gpu` or `cpu` (the CLI spelling).
    pub fn parse(text: &str) -> Option<Self> {
        match text {
            "auto" => Some(Self::Auto),
            "gpu" => Some(Self::Gpu),
            "cpu" => Some(Self::Cpu),
            _ => None,
        }
    }
}

/// A backend made for a run, and why it is not the GPU one when [`BackendChoice::Auto`] took
/// the CPU twins.
#[derive(Debug)]
pub struct ChosenBackend {
    pub backend: Box<dyn Backend>,
    /// `Some(reason)` when `Auto` found no hardware adapter and runs on the CPU twins.
    pub fallback: Option<String>,
}

/// Makes the backend `choice` asks for.
pub fn create_backend(choice: BackendChoice) -> Result<ChosenBackend, GpuError> {
    create_backend_with(choice, FeedbackMode::default())
}

/// [`create_backend`] with the GPU backend's [`FeedbackMode`] (the CPU twins always answer at
/// once).
pub fn create_backend_with(
    choice: BackendChoice,
    feedback: FeedbackMode,
) -> Result<ChosenBackend, GpuError> {
    let gpu = |ctx: GpuContext| {
        let mut b = GpuBackend::timed(Arc::new(ctx));
        b.set_feedback_mode(feedback);
        Box::new(b) as Box<dyn Backend>
    };
    match choice {
        BackendChoice::Cpu => Ok(ChosenBackend {
            backend: Box::new(CpuBackend),
            fallback: None,
        }),
        BackendChoice::Gpu => Ok(ChosenBackend {
            backend: gpu(GpuContext::new(None)?),
            fallback: None,
        }),
        BackendChoice::Auto => match GpuContext::new(None) {
            Ok(ctx) if ctx.is_software() => Ok(ChosenBackend {
                backend: Box::new(CpuBackend),
                fallback: Some(format!(
                    "the only adapter is a software one, {}, which runs the passes on this \
                     machine's cores more slowly than the CPU twins (--backend gpu uses it anyway)",
                    ctx.describe()
                )),
            }),
            Ok(ctx) => Ok(ChosenBackend {
                backend: gpu(ctx),
                fallback: None,
            }),
            Err(e) => Ok(ChosenBackend {
                backend: Box::new(CpuBackend),
                fallback: Some(e.to_string()),
            }),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cli_spellings_parse_and_nothing_else() {
        assert_eq!(BackendChoice::parse("gpu"), Some(BackendChoice::Gpu));
        assert_eq!(FeedbackMode::parse("auto"), Some(FeedbackMode::Auto));
        assert_eq!(FeedbackMode::parse("wait"), Some(FeedbackMode::Wait));
        assert_eq!(
            FeedbackMode::parse("pipelined"),
            Some(FeedbackMode::Pipelined)
        );
        for bad in ["", "Wait", "sync", "pipeline"] {
            assert_eq!(FeedbackMode::parse(bad), None, "{bad:?}");
        }
    }
}
