//! Running long core work off the GIL while staying responsive to Python.
//!
//! The job runs on a scoped worker thread. The calling thread releases the GIL and waits for
//! it in slices of [`POLL_INTERVAL`]; between slices it re-attaches briefly to report
//! progress and to let Python handle signals (Ctrl-C). An exception from either cancels the
//! job through its [`RenderControl`], waits for the worker to stop and is then re-raised.
//! A panic on the worker is caught and raised as `CrepuscularError`, never unwound into Python.

use std::panic::{self, AssertUnwindSafe};
use std::sync::mpsc::{self, RecvTimeoutError};
use std::time::Duration;

use crepuscular::RenderControl;
use pyo3::prelude::*;

use crate::errors::{internal_error, to_py_err};

/// How often the waiting thread re-attaches to Python.
pub const POLL_INTERVAL: Duration = Duration::from_millis(50);

/// Runs `job` on a worker thread with the GIL released and returns its result.
///
/// `progress`, when given, is called on this thread with the fraction done (a float in
/// [0, 1]) whenever it has grown, and once with 1.0 after the job succeeded.
pub fn run_detached<'py, T, F>(
    py: Python<'py>,
    progress: Option<&Bound<'py, PyAny>>,
    job: F,
) -> PyResult<T>
where
    T: Send,
    F: FnOnce(&RenderControl) -> crepuscular::Result<T> + Send,
{
    let control = RenderControl::new();
    let control = &control;
    let mut reported = 0.0_f32;

    let outcome = std::thread::scope(|scope| {
        let (sender, mut receiver) = mpsc::sync_channel(1);
        scope.spawn(move || {
            let result = panic::catch_unwind(AssertUnwindSafe(|| job(control)));
            // The receiver outlives this thread (the scope joins it first).
            let _ = sender.send(result);
        });
        loop {
            // `&mut` so that the closure is `Send` although the receiver is not `Sync`.
            let waiting = &mut receiver;
            match py.detach(move || waiting.recv_timeout(POLL_INTERVAL)) {
                Ok(result) => return Ok(result),
                Err(RecvTimeoutError::Disconnected) => {
                    let payload: Box<dyn std::any::Any + Send> =
                        Box::new("the worker thread exited without a result");
                    return Ok(Err(payload));
                }
                Err(RecvTimeoutError::Timeout) => {}
            }
            if let Err(err) = poll(py, control, progress, &mut reported) {
                control.cancel();
                let draining = &mut receiver;
                // Whatever the worker produced is dropped: the Python exception wins.
                let _ = py.detach(move || draining.recv());
                return Err(err);
            }
        }
    });

    let value = match outcome? {
        Ok(result) => result.map_err(to_py_err)?,
        Err(payload) => return Err(internal_error(payload.as_ref())),
    };
    if let Some(callback) = progress {
        callback.call1((1.0_f64,))?;
    }
    Ok(value)
}

/// One poll on the calling thread, attached to Python.
fn poll(
    py: Python<'_>,
    control: &RenderControl,
    progress: Option<&Bound<'_, PyAny>>,
    reported: &mut f32,
) -> PyResult<()> {
    py.check_signals()?;
    if let Some(callback) = progress {
        let fraction = control.fraction();
        if fraction > *reported {
            *reported = fraction;
            callback.call1((f64::from(fraction),))?;
        }
    }
    Ok(())
}
