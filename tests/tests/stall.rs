//! A run whose link goes dark says so in its report: a real server, the real client session
//! and the link emulator, which drops every packet both ways for a few seconds in the middle of
//! the run. The report's events must name the stall — with the client asking for treelets, so
//! the server or the link is blamed, not the client — and then the progress that follows once
//! the link is back; the view must still converge exactly. Without the stall watch
//! (`arbor_client_session::stall`) a dark link and a slow one give the same curves.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use arbor_client_core::backend::CpuBackend;
use arbor_client_core::camera::CameraPath;
use arbor_client_session::headless::run_headless_with;
use arbor_client_session::stall::STALL_SECONDS;
use arbor_tests::link::{LinkConfig, LinkEmulator};
use arbor_tests::streaming::{full, headless, reference, scene_bytes, serve};

/// A slow link, so the view is still far from converged when it goes dark.
const DELAY: Duration = Duration::from_millis(20);
const RATE: u64 = 400_000;
/// The cycle after which the link goes dark.
const DARK_AFTER: u32 = 8;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_link_that_goes_dark_is_reported_as_a_stall_and_the_view_still_converges() {
    let served = serve("points/lion_takanawa.copc.laz", "lion", 1024).await;
    let lit = LinkConfig::wan(DELAY, RATE);
    let link = Arc::new(
        LinkEmulator::start(served.server.quic_addr, lit.clone())
            .await
            .unwrap(),
    );
    let full = full(&served);
    let reference = reference(&served, &full, &CameraPath::Static, 0, &mut CpuBackend);
    let mut cfg = headless(
        link.local_addr(),
        &served,
        CameraPath::Static,
        scene_bytes(&served) * 2,
    );
    cfg.reference = Some(reference);
    cfg.until_converged = true;
    // Cycles of at least 4 ms: at most 80 s, where the run takes about 10.
    cfg.cycles = 20_000;
    let dark_for = Duration::from_secs_f64(STALL_SECONDS + 1.5);
    // (when the link went dark, whether it is lit again, the share known when it went dark)
    let darkness: Arc<Mutex<Option<(Instant, bool, f64)>>> = Arc::default();
    let observer = {
        let (link, darkness, lit) = (link.clone(), darkness.clone(), lit.clone());
        move |c: &arbor_client_session::headless::CycleView<'_>| {
            let mut d = darkness.lock().unwrap();
            match *d {
                None if c.record.cycle + 1 >= DARK_AFTER => {
                    link.set_config(lit.clone().with_loss(1.0)).unwrap();
                    *d = Some((Instant::now(), false, c.record.known_share));
                    assert!(
                        c.record.error.max > 0.0 || c.record.known_share < 1.0,
                        "converged before the link went dark: this tests nothing"
                    );
                }
                Some((since, false, share)) if since.elapsed() >= dark_for => {
                    link.set_config(lit.clone()).unwrap();
                    *d = Some((since, true, share));
                }
                _ => {}
            }
        }
    };
    let handle = tokio::runtime::Handle::current();
    let run = tokio::task::spawn_blocking(move || {
        run_headless_with(cfg, &handle, Box::new(CpuBackend), observer)
    })
    .await
    .unwrap()
    .expect("the run");
    for e in &run.report.events {
        eprintln!("event at cycle {} ({:.2} s): {}", e.cycle, e.time_s, e.what);
    }
    let (_, relit, share) = darkness.lock().unwrap().expect("the link went dark");
    assert!(relit, "the run ended before the link was lit again");
    eprintln!(
        "dark after cycle {DARK_AFTER} with {:.1} % of the view known; converged at {:?} of {} \
         cycles",
        share * 100.0,
        run.converged_at,
        run.report.records.len()
    );
    let events = &run.report.events;
    assert_eq!(events.len(), 2, "a stall and progress again: {events:?}");
    assert!(
        events[0].what.starts_with("stalled")
            && events[0].what.contains("the server or the link stalled"),
        "{}",
        events[0].what
    );
    assert!(events[0].cycle >= DARK_AFTER, "{events:?}");
    assert!(
        events[1].what.starts_with("progress again"),
        "{}",
        events[1].what
    );
    assert!(
        events[1].time_s - events[0].time_s < 30.0,
        "progress came back late: {events:?}"
    );
    run.converged_at
        .expect("the view converges once the link is back");
    let last = run.report.records.last().unwrap();
    assert_eq!(last.image_rmse, Some(0.0), "final image RMSE");
}
