//! A connection's life after `Hello`: one [`Handler`] holding the connection's state, with one
//! method per event of its main loop (a request list or another control frame, a treelet handed
//! over by the dispatcher, a treelet stream ending, the 50 ms tick, the window following the
//! congestion window while treelets are in flight, shutdown), in the
//! mini-redis style. [`serve`] runs `Hello`, registers the connection with the scheduler and
//! drives the loop; each event method returns `Some(end)` when the connection must end.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use arbor_proto::limits::MAX_REQUEST_ITEMS;
use arbor_proto::wire::{ErrorCode, Frame, ViewHint};
use arbor_proto::{Channel, TreeletId};
use tokio::sync::{mpsc, oneshot};
use tokio::task::JoinSet;

use super::batches::Batches;
use super::connection::{ControlReader, End, Greeting, close, hello};
use super::push::{
    DeferredPlans, LentAnchors, PlannedList, PushAnchors, ShapeMissing, WorldCube, cut_has_work,
    cut_list, cut_saves, frustum_list, push_cap,
};
use super::readers::ReadFor;
use super::schedule::{ConnectionConfig, ConnectionId, ListOutcome, window_for};
use super::shared::Shared;
use super::shutdown::Shutdown;
use super::streams::{
    CANCEL_CODE, OpenStream, Outcome, ProgressClock, StreamCtx, open_in_order, send_batch,
};
use super::timeline::Event;
use super::treelets::ServedScene;
use super::visibility::{VisibleCut, frame_rays, same_view};

/// How often the window and the slow-reader watchdog are updated.
const TICK: Duration = Duration::from_millis(50);
/// How often, while treelets are in flight, the window follows the congestion window between
/// deliveries. A delivery is a whole batch acknowledged, a round trip or more after it was
/// written, and the tick comes every 50 ms; meanwhile slow start doubles the congestion window
/// every round trip, and a resumed connection (`path_memory`) jumps to half its saved window at
/// its first acknowledgement. Waiting for either held a connection below what its path took:
/// the whole lion-4k over the link emulator came 4 % sooner with this, on a first connection
/// and on a resumed one (docs/measurements.md, stop 58).
const WINDOW_FOLLOW: Duration = Duration::from_millis(10);
/// Added to the RTT for the redelivery guard: about one client cycle.
const CLIENT_CYCLE: Duration = Duration::from_millis(50);

/// The connection's whole service: `Hello`, then the main loop. Returns how it ends.
pub(super) async fn serve(
    shared: &Arc<Shared>,
    id: ConnectionId,
    conn: &quinn::Connection,
    mut shutdown: Shutdown,
    hello_deadline: tokio::time::Instant,
    control: &mut Option<quinn::SendStream>,
) -> End {
    let shutting_down = || End::Close {
        code: ErrorCode::ShuttingDown,
        reason: "server shutting down".into(),
        goodbye: true,
    };
    if shutdown.deadline().is_some() {
        return shutting_down();
    }
    let greeted = tokio::select! {
        r = tokio::time::timeout_at(hello_deadline, hello(shared, conn, control)) => match r {
            Ok(r) => r,
            Err(_) => Err(close(
                ErrorCode::ProtocolViolation,
                format!("no Hello within {} ms", shared.config.hello_timeout_ms),
            )),
        },
        _ = shutdown.recv() => Err(shutting_down()),
    };
    let Greeting {
        mut reader,
        scene,
        channels,
        send_root,
        view,
        grant,
    } = match greeted {
        Ok(g) => g,
        Err(end) => return end,
    };
    let scene_name = grant.scene.clone();
    if !shared.access.enter(id.0, grant, conn.clone()) {
        return close(
            ErrorCode::Unauthorized,
            format!("access to scene {scene_name:?} revoked"),
        );
    }
    let root = scene.stored.description.root_treelet;
    let mut handler = match Handler::register(shared, id, conn, scene, channels) {
        Ok(h) => h,
        Err(end) => return end,
    };
    // The root, unasked: as a list of sequence 0, which the client's first list (1 or more)
    // replaces; with a view, as a deep list whose pushes are the view's refinement below the
    // root, as deep as the view refines (the client has measured nothing yet).
    let first = match (send_root, view) {
        (false, _) => None,
        (true, None) => handler.on_request_list(0, PlannedList::plain(vec![(root, f32::MAX)])),
        (true, Some(view)) => handler.on_hello_view(root, &view),
    };
    if let Some(end) = first {
        return end;
    }
    let end = handler.run(&mut reader, &mut shutdown).await;
    handler.finish(&end).await;
    end
}

/// A deep request list as applied: its sequence number, view, items and prefetch start.
type DeepList = (u64, ViewHint, Vec<(TreeletId, f32, f32)>, usize);

/// The state of one connection's main loop.
struct Handler {
    shared: Arc<Shared>,
    id: ConnectionId,
    conn: quinn::Connection,
    ctx: Arc<StreamCtx>,
    /// Batches the dispatcher hands to this connection, one per stream.
    jobs: mpsc::UnboundedReceiver<Vec<TreeletId>>,
    /// Asks the opener for the next stream, in rank order.
    opens: mpsc::UnboundedSender<oneshot::Sender<OpenStream>>,
    opener: AbortOnDrop<()>,
    /// One task per batch in flight, with its batch number.
    streams: JoinSet<(u64, Vec<TreeletId>, Outcome)>,
    /// The batches in flight, each with how to cancel it.
    batches: Batches<oneshot::Sender<ErrorCode>>,
    /// Rank of the next treelet started under the current list (0 = the list's first).
    rank: i32,
    /// The client may still send frames.
    reading: bool,
    window: usize,
    treelet_count: u32,
    /// The latest visible cut computed for this connection's view, and whether its pushes
    /// replace the frustum plan's ([`cut_saves`]).
    cut: Option<(Arc<VisibleCut>, bool)>,
    /// The cut being computed, off the async workers, with whether it saves enough.
    cut_job: Option<tokio::task::JoinHandle<Option<(VisibleCut, bool)>>>,
    /// The view whose fine cut the scene's gate skipped (`ServedScene::should_cast_fine_cut`):
    /// asked once per view, not once per list.
    fine_skipped: Option<ViewHint>,
    /// The last deep list applied (sequence, view, items, prefetch start): re-planned when its
    /// view's cut arrives.
    last_deep: Option<DeepList>,
    /// What was sent for the view the connection rests on: the frustum plan goes on below it.
    /// Lent to the plan being made on a reader, if any.
    anchors: LentAnchors,
    /// The frustum plan being made on a reader thread, if any ([`Self::start_plan`]); its
    /// output is `None` when it panicked (the anchors went with it).
    plan_job: Option<AbortOnDrop<Option<PlannedOnReader>>>,
    /// Which deep list that plan is for, which waits for pushes, and whether a plan that comes
    /// back is still wanted.
    plans: DeferredPlans<DeepList>,
}

/// What a plan made on a reader gives back: its list (`None`: it failed) and the anchors.
type PlannedOnReader = (Option<PlannedList>, PushAnchors);

impl Handler {
    /// Registers the accepted connection with the scheduler and starts its stream opener.
    fn register(
        shared: &Arc<Shared>,
        id: ConnectionId,
        conn: &quinn::Connection,
        scene: Arc<ServedScene>,
        channels: Vec<Channel>,
    ) -> Result<Handler, End> {
        let scene_name = scene.stored.description.name.clone();
        shared.state.update_session(id.0, |s| {
            s.scene = scene_name.clone();
            s.set_channels(&channels);
        });
        tracing::info!(channels = ?channels.iter().map(|c| c.name()).collect::<Vec<_>>(), "hello accepted");
        let (route, jobs) = mpsc::unbounded_channel();
        // Twice the initial congestion window from the start (as `on_tick` keeps it), in the
        // scene's mean stored treelet, so a fresh connection is not held to `window_min` until
        // the first tick (a whole small scene is sent before it).
        let stats = &scene.stored.description.stats;
        let stored = stats.stored_bytes();
        let mean = (stored / u64::from(scene.treelet_count().max(1))).max(256);
        let window = (2 * shared.config.initial_window).div_ceil(mean).clamp(
            shared.config.window_min as u64,
            shared.config.window_max as u64,
        ) as usize;
        // Worked out before the scheduler's lock, which every connection's scheduling takes.
        let recent_deliveries = shared.config.memory_plan().recent_deliveries;
        {
            let mut core = shared.core();
            core.routes.insert(id, route);
            let config = ConnectionConfig {
                window,
                max_queue: MAX_REQUEST_ITEMS,
                redelivery_guard: ConnectionConfig::default().redelivery_guard,
                // From the first deep list on, with visible cuts (`on_deep_request_list`): a
                // client of plain lists gets no cut and pays no record per delivery.
                remember_deliveries: false,
                recent_deliveries,
            };
            if let Err(e) = core.sched.add_connection(id, config) {
                tracing::error!("{e}");
                return Err(close(ErrorCode::Internal, "connection registered twice"));
            }
        }
        let treelet_count = scene.treelet_count();
        let ctx = Arc::new(StreamCtx {
            shared: shared.clone(),
            id,
            conn: conn.clone(),
            scene,
            channels,
            clock: ProgressClock::new(Instant::now()),
            bytes_sent: AtomicU64::new(0),
            treelets_sent: AtomicU64::new(0),
        });
        let (opens, open_requests) = mpsc::unbounded_channel();
        let opener = AbortOnDrop(tokio::spawn(open_in_order(ctx.clone(), open_requests)));
        Ok(Handler {
            shared: shared.clone(),
            id,
            conn: conn.clone(),
            ctx,
            jobs,
            opens,
            opener,
            streams: JoinSet::new(),
            batches: Batches::default(),
            rank: 0,
            reading: true,
            window,
            treelet_count,
            cut: None,
            cut_job: None,
            fine_skipped: None,
            last_deep: None,
            anchors: LentAnchors::from(PushAnchors::default()),
            plan_job: None,
            plans: DeferredPlans::default(),
        })
    }

    /// The main loop: waits for the next event and hands it to its method.
    async fn run(&mut self, reader: &mut ControlReader, shutdown: &mut Shutdown) -> End {
        let mut tick = tokio::time::interval(TICK);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let mut follow = tokio::time::interval(WINDOW_FOLLOW);
        follow.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            let end = tokio::select! {
                frame = reader.read_frame(), if self.reading => self.on_frame(frame),
                Some(batch) = self.jobs.recv() => self.on_batch(batch),
                Some(joined) = self.streams.join_next(), if !self.streams.is_empty() => {
                    match joined {
                        Ok((id, batch, outcome)) => self.on_stream_end(id, &batch, outcome),
                        Err(_) => None,
                    }
                }
                cut = join_cut(&mut self.cut_job), if self.cut_job.is_some() => self.on_cut(cut),
                planned = join_plan(&mut self.plan_job), if self.plan_job.is_some() => {
                    self.on_planned(planned)
                }
                _ = tick.tick() => self.on_tick(),
                _ = follow.tick(), if !self.streams.is_empty() => {
                    self.update_window();
                    None
                }
                deadline = shutdown.recv() => Some(self.drain(deadline).await),
                e = self.conn.closed() => Some(End::Lost(e)),
            };
            if let Some(end) = end {
                return end;
            }
        }
    }

    /// A control frame from the client (or the end of its control stream).
    fn on_frame(&mut self, frame: Result<Option<Frame>, End>) -> Option<End> {
        match frame {
            Ok(Some(Frame::RequestList { seq, items })) => {
                self.on_request_list(seq, PlannedList::plain(items))
            }
            Ok(Some(Frame::DeepRequestList {
                seq,
                view,
                items,
                prefetch_from,
            })) => self.on_deep_request_list(seq, &view, &items, prefetch_from as usize),
            Ok(Some(Frame::RankedRequestList {
                seq,
                view,
                items,
                prefetch_from,
            })) => self.on_deep_request_list(
                seq,
                &view,
                &arbor_proto::wire::ranked_as_deep(&items),
                prefetch_from as usize,
            ),
            Ok(Some(Frame::Goodbye { code })) => Some(close(
                ErrorCode::NoError,
                format!("client said goodbye ({code})"),
            )),
            Ok(Some(Frame::Error { code, message })) => Some(close(
                ErrorCode::NoError,
                format!("client reported an error: {code}: {message}"),
            )),
            Ok(Some(other)) => Some(close(
                ErrorCode::ProtocolViolation,
                format!("unexpected {:?} frame after Hello", other.frame_type()),
            )),
            Ok(None) => {
                // The client will send no more lists; keep serving the current one.
                tracing::debug!("control stream finished by the client");
                self.reading = false;
                None
            }
            Err(end) => Some(end),
        }
    }

    /// A new request list (its last `pushed` items planned by the server): replaces the
    /// scheduler's queue and resets the streams of treelets in flight that it no longer names.
    fn on_request_list(&mut self, seq: u64, list: PlannedList) -> Option<End> {
        let count = self.treelet_count;
        if let Some((t, _)) = list.items.iter().find(|(t, _)| t.0 >= count) {
            return Some(close(
                ErrorCode::UnknownTreelet,
                format!("treelet {} does not exist (the scene has {count})", t.0),
            ));
        }
        let m = &self.shared.state.metrics;
        m.request_lists.fetch_add(1, Ordering::Relaxed);
        m.request_items
            .fetch_add(list.items.len() as u64, Ordering::Relaxed);
        self.apply_list(seq, list, false)
    }

    /// Hands a list to the scheduler — a new one, or (`replan`) the last one again with pushes
    /// planned anew — and resets the streams it no longer wants.
    fn apply_list(&mut self, seq: u64, list: PlannedList, replan: bool) -> Option<End> {
        let PlannedList {
            items,
            pushed,
            prefetch_below,
            set_apart,
        } = list;
        let m = &self.shared.state.metrics;
        m.pushes_planned.fetch_add(pushed as u64, Ordering::Relaxed);
        m.prefetch_set_apart
            .fetch_add(set_apart as u64, Ordering::Relaxed);
        let named = self
            .shared
            .state
            .timeline
            .is_on()
            .then(|| items.iter().map(|&(id, _)| id).collect::<Vec<_>>());
        let outcome = {
            let mut core = self.shared.core();
            let now = Instant::now();
            match (prefetch_below, replan) {
                (Some(below), _) => core
                    .sched
                    .handle_list_with_prefetch(self.id, seq, items, below, replan, now),
                (None, true) => core.sched.handle_replanned_list(self.id, seq, items, now),
                (None, false) => core.sched.handle_request_list(self.id, seq, items, now),
            }
        };
        match outcome {
            Ok(ListOutcome::Applied {
                obsolete_in_flight, ..
            }) => {
                self.plans.applied();
                self.rank = 0;
                self.cancel_obsolete(&obsolete_in_flight);
                if let Some(mut listed) = named {
                    let pushed = listed.split_off(listed.len().saturating_sub(pushed));
                    let session = self.id.0;
                    self.shared.state.timeline.record(|| Event::Listed {
                        session,
                        at: Instant::now(),
                        listed,
                        pushed,
                    });
                }
            }
            Ok(ListOutcome::Stale { last_seq }) => {
                tracing::debug!(seq, last_seq, replan, "stale request list ignored");
            }
            Err(e) => {
                tracing::error!("{e}");
                return Some(close(ErrorCode::Internal, "scheduler lost the connection"));
            }
        }
        if !replan {
            self.shared
                .state
                .update_session(self.id.0, |s| s.request_lists += 1);
        }
        self.shared.wake.notify_one();
        None
    }

    /// A request list with the client's view: the listed items, then the descendants the view
    /// would refine below them (`push.rs`), within the free slots the client announced, at
    /// priorities below every listed item.
    fn on_deep_request_list(
        &mut self,
        seq: u64,
        view: &ViewHint,
        items: &[(TreeletId, f32, f32)],
        prefetch_from: usize,
    ) -> Option<End> {
        let count = self.treelet_count;
        if let Some((t, _, _)) = items.iter().find(|(t, _, _)| t.0 >= count) {
            return Some(close(
                ErrorCode::UnknownTreelet,
                format!("treelet {} does not exist (the scene has {count})", t.0),
            ));
        }
        // A view named twice in a row (or `Hello`'s) is resting: worth a visible cut. A moving
        // camera's views are never cast; its pushes follow the frustum plan.
        if self.shared.config.visibility_grid > 0 {
            if self.last_deep.is_none() {
                let _ = self.shared.core().sched.remember_deliveries(self.id);
            }
            let resting = seq == 0
                || self
                    .last_deep
                    .as_ref()
                    .is_some_and(|(_, last, _, _)| same_view(last, view));
            self.last_deep = Some((seq, *view, items.to_vec(), prefetch_from));
            if resting {
                self.start_cut();
            }
        }
        if let Some(list) = self.plan_now(view, items, prefetch_from) {
            self.plans.planned_at_once();
            return self.on_request_list(seq, list);
        }
        // A shape the cache lacks must be read from the pool, which may wait for the disk: the
        // listed items go now, as listed, and their pushes once a reader has planned them
        // (`start_plan`). Planned on the worker, the city's resting soak with its pool outside
        // the page cache waited 196–209 ms for a list's first treelet (p99), and one run left
        // hellos unanswered for 10 s (docs/measurements.md, stop 67).
        let listed = items.iter().map(|&(id, p, _)| (id, p)).collect();
        if let Some(end) = self.on_request_list(seq, PlannedList::plain(listed)) {
            return Some(end);
        }
        self.plans
            .defer((seq, *view, items.to_vec(), prefetch_from));
        self.start_plan();
        None
    }

    /// The list for a deep request, if it can be made now on this worker: pushes from the
    /// view's visible cut when one answers it, with the prefetch it does not hold set apart
    /// ([`cut_list`]), else from the frustum plan below the listed treelets and what was
    /// already sent for the same view ([`PushAnchors`]) when every shape that plan looks up is
    /// in the shape cache. Without a cut nothing tells a guess from a need, so nothing is set
    /// apart: the frustum plan also pushes below prefetch items, and holding those back would
    /// hold back their pushes too. `None`: the plan needs the pool, or the anchors are lent to
    /// a plan that does ([`Self::start_plan`]).
    fn plan_now(
        &mut self,
        view: &ViewHint,
        items: &[(TreeletId, f32, f32)],
        prefetch_from: usize,
    ) -> Option<PlannedList> {
        if let Some((cut, _)) = self
            .cut
            .as_ref()
            .filter(|(c, followed)| *followed && c.complete && c.answers(view))
        {
            let core = self.shared.core();
            return Some(cut_list(
                cut,
                view,
                items,
                prefetch_from,
                MAX_REQUEST_ITEMS,
                |t| core.sched.was_delivered(self.id, t),
            ));
        }
        let scene = self.ctx.scene.clone();
        let cube = WorldCube::of(&scene.stored.description);
        let max_items = self.max_planned_items(items.len());
        let anchors = self.anchors.get_mut()?;
        let mut hits = 0;
        let list = frustum_list(cube, view, items, anchors, max_items, |id| {
            let shape = scene.cached_shape(id).ok_or(ShapeMissing)?;
            hits += 1;
            Ok(Some(shape))
        })
        .ok()?;
        scene.count_shape_hits(hits);
        Some(list)
    }

    /// Most items of a planned list of `listed` items: a few windows of pushes beyond them
    /// (more would be planned again before they could go out).
    fn max_planned_items(&self, listed: usize) -> usize {
        (listed + push_cap(self.window)).min(MAX_REQUEST_ITEMS)
    }

    /// Starts planning the pushes of the deep list awaiting them on a reader thread, with the
    /// anchors lent to it, unless a plan is being made already (its end starts the next).
    fn start_plan(&mut self) {
        if self.anchors.is_lent() {
            return;
        }
        let Some((_, view, items, _)) = self.plans.start(|list| list.0) else {
            return;
        };
        let Some(mut anchors) = self.anchors.lend() else {
            return;
        };
        let scene = self.ctx.scene.clone();
        let cube = WorldCube::of(&scene.stored.description);
        let max_items = self.max_planned_items(items.len());
        let shared = self.shared.clone();
        shared
            .state
            .metrics
            .plans_on_readers
            .fetch_add(1, Ordering::Relaxed);
        let task = tokio::spawn(async move {
            shared
                .readers
                .read(ReadFor::Plan, move || {
                    let list = frustum_list(cube, &view, &items, &mut anchors, max_items, |id| {
                        Ok(scene.shape(id))
                    });
                    (list.ok(), anchors)
                })
                .await
                .ok()
        });
        self.plan_job = Some(AbortOnDrop(task));
    }

    /// A plan made on a reader is back: the anchors come home, and its list replaces the one
    /// applied without pushes, unless another list was applied since. Then the deep list
    /// awaiting pushes now, if it is the one applied last, is planned.
    fn on_planned(&mut self, planned: Option<PlannedOnReader>) -> Option<End> {
        let (list, anchors) = match planned {
            Some((list, anchors)) => (list, Some(anchors)),
            None => {
                tracing::error!("a push plan failed on its reader; its list went as listed");
                (None, None)
            }
        };
        self.anchors.give_back(anchors);
        if let (Some(seq), Some(list)) = (self.plans.finish(), list)
            && let Some(end) = self.apply_list(seq, list, true)
        {
            return Some(end);
        }
        let (seq, view, items, prefetch_from) = self.plans.take_waiting()?;
        match self.plan_now(&view, &items, prefetch_from) {
            Some(list) => self.apply_list(seq, list, true),
            None => {
                self.plans.defer((seq, view, items, prefetch_from));
                self.start_plan();
                None
            }
        }
    }

    /// Starts computing the visible cut of the last deep list's view on a blocking thread — the
    /// coarse one, or the fine one once the coarse one answers the view and is followed —
    /// unless visible cuts are off, one is being computed, the list leaves a cut nothing to
    /// decide ([`cut_has_work`]: a budget-bound client's lists fill every free slot
    /// themselves), or the last cut answers this view at the finest grid configured (or was
    /// not worth following: a finer cast would not change that much). Neither grid
    /// exceeds the client's own frame ([`frame_rays`]); the fine one is cast from the coarse
    /// one, unless the scene's last fine cuts went unused (`FineCutGate`). The same thread
    /// decides whether the cut saves enough against the frustum plan to be followed, and stops
    /// casting it as soon as it has grown too large for that.
    fn start_cut(&mut self) {
        let Some((_, view, items, prefetch_from)) = &self.last_deep else {
            return;
        };
        let (view, has_work) = (*view, cut_has_work(view, items.len(), *prefetch_from));
        let view = &view;
        // No finer than the client's own frame: a small client's view needs no more rays.
        let rays = frame_rays(view);
        let coarse = self.shared.config.visibility_grid.min(rays);
        let fine = self.shared.config.visibility_fine_grid.min(rays);
        if coarse == 0 || self.cut_job.is_some() {
            return;
        }
        if !has_work {
            self.shared
                .state
                .metrics
                .cuts_without_work
                .fetch_add(1, Ordering::Relaxed);
            return;
        }
        let (grid, coarse_cut) = match self.cut.as_ref().filter(|(c, _)| c.answers(view)) {
            None => (coarse, None),
            Some((c, true)) if fine > c.grid => {
                if self
                    .fine_skipped
                    .as_ref()
                    .is_some_and(|v| same_view(v, view))
                {
                    return;
                }
                if !self.ctx.scene.should_cast_fine_cut() {
                    self.fine_skipped = Some(*view);
                    self.shared
                        .state
                        .metrics
                        .fine_cuts_skipped
                        .fetch_add(1, Ordering::Relaxed);
                    return;
                }
                (fine, Some(c.clone()))
            }
            Some(_) => return,
        };
        let scene = self.ctx.scene.clone();
        let budget = self.shared.config.visibility_cache_bytes;
        let share = self.shared.config.visibility_follow_share;
        let view = *view;
        self.cut_job = Some(tokio::task::spawn_blocking(move || {
            let seed = coarse_cut.as_ref().map_or(&[][..], |c| &c.treelets);
            let d = &scene.stored.description;
            let saves = |treelets: usize| {
                cut_saves(
                    WorldCube::of(d),
                    &view,
                    treelets,
                    d.root_treelet,
                    share,
                    |id| scene.shape(id),
                )
            };
            let cut = scene.visible_cut(&view, grid, seed, budget, saves)?;
            let followed = !cut.abandoned && saves(cut.treelets.len());
            if coarse_cut.is_some() {
                scene.record_fine_cut(followed && cut.complete);
            }
            Some((cut, followed))
        }));
    }

    /// A visible cut is ready: kept, and, if it saves enough to be followed, the last deep list
    /// re-planned with it when it answers that list's view (the pushes the frustum plan chose
    /// are replaced).
    fn on_cut(
        &mut self,
        cut: Result<Option<(VisibleCut, bool)>, tokio::task::JoinError>,
    ) -> Option<End> {
        let (cut, followed) = match cut {
            Ok(Some((c, followed))) => (Arc::new(c), followed),
            Ok(None) => return None,
            Err(e) => {
                tracing::warn!("visible cut failed: {e}");
                return None;
            }
        };
        tracing::debug!(
            treelets = cut.treelets.len(),
            rays = cut.rays_cast,
            complete = cut.complete,
            followed,
            took_ms = cut.took.as_secs_f64() * 1e3,
            "visible cut"
        );
        self.shared
            .state
            .metrics
            .visible_cuts
            .fetch_add(1, Ordering::Relaxed);
        self.cut = Some((cut.clone(), followed));
        let (seq, view, items, prefetch_from) = self.last_deep.clone()?;
        if !(followed && cut.complete && cut.answers(&view)) {
            return None;
        }
        // A cut that answers the view is planned from at once.
        let list = self.plan_now(&view, &items, prefetch_from)?;
        self.start_cut();
        self.apply_list(seq, list, true)
    }

    /// `Hello`'s view ([`arbor_proto::wire::HELLO_VIEW`], eye in root-cube units): the root
    /// and the view's refinement below it, as a deep list of sequence 0.
    fn on_hello_view(&mut self, root: TreeletId, view: &ViewHint) -> Option<End> {
        let d = &self.ctx.scene.stored.description;
        let view = ViewHint {
            eye: std::array::from_fn(|i| d.origin[i] + view.eye[i] * d.edge),
            ..*view
        };
        if let Err(e) = view.check() {
            return Some(close(
                ErrorCode::ProtocolViolation,
                format!("Hello view in this scene's world: {e}"),
            ));
        }
        self.on_deep_request_list(0, &view, &[(root, f32::MAX, ViewHint::MAX_ERROR)], 1)
    }

    /// Resets the streams of batches the latest list wants nothing of any more; a batch with
    /// a treelet still wanted goes on (the few unwanted ones in it arrive anyway).
    fn cancel_obsolete(&mut self, obsolete: &[TreeletId]) {
        for tx in self.batches.obsolete(obsolete) {
            let _ = tx.send(CANCEL_CODE);
        }
    }

    /// The dispatcher handed over a batch (treelets adjacent in rank, at most
    /// [`super::schedule::batch_limit`] of the window): start a stream task for it, ranked after
    /// the ones started before under the same list.
    fn on_batch(&mut self, batch: Vec<TreeletId>) -> Option<End> {
        self.anchors.note_sent(&batch);
        if let Some(e) = self.conn.close_reason() {
            // Lost under our feet: do not churn through the queue opening streams.
            return Some(End::Lost(e));
        }
        if self.streams.is_empty() {
            // Idle until now: the watchdog counts from here.
            self.ctx.progress();
        }
        let (tx, rx) = oneshot::channel();
        let id = self.batches.start(&batch, tx);
        let (open_tx, open_rx) = oneshot::channel();
        let _ = self.opens.send(open_tx);
        let priority = self.rank.saturating_neg();
        self.rank = self.rank.saturating_add(batch.len() as i32);
        let sending = send_batch(self.ctx.clone(), batch, priority, open_rx, rx);
        self.streams.spawn(async move {
            let (batch, outcome) = sending.await;
            (id, batch, outcome)
        });
        None
    }

    /// Batch `id`'s stream task ended. Its treelets may already be in a newer batch (the
    /// scheduler hears of their end before this handler does): only this batch's record goes.
    fn on_stream_end(&mut self, id: u64, batch: &[TreeletId], outcome: Outcome) -> Option<End> {
        self.batches.end(id);
        match outcome {
            Outcome::Failed(reason) => {
                tracing::error!(treelets = ?batch, "{reason}");
                Some(close(
                    ErrorCode::Internal,
                    format!("treelets {batch:?} unavailable"),
                ))
            }
            Outcome::Delivered => {
                // A delivery is news of the path: the window follows the congestion window
                // now, not at the next tick (a small scene is sent whole before a tick).
                self.update_window();
                None
            }
            Outcome::Lost | Outcome::Cancelled | Outcome::StoppedByPeer => {
                self.anchors.note_unsent(batch);
                None
            }
        }
    }

    /// Every [`TICK`]: the slow-reader watchdog, the window from quinn's RTT and congestion
    /// window, the redelivery guard and the treelets it deferred, the session's figures.
    fn on_tick(&mut self) -> Option<End> {
        let config = &self.shared.config;
        if !self.streams.is_empty()
            && self.ctx.clock.stalled_for(Instant::now()) >= config.slow_reader_timeout()
        {
            return Some(close(
                ErrorCode::SlowReader,
                format!(
                    "{} treelets in flight and no progress for {} ms",
                    self.streams.len(),
                    config.slow_reader_timeout_ms
                ),
            ));
        }
        let rtt = self.update_window();
        let (stats, released) = {
            let mut core = self.shared.core();
            let _ = core.sched.set_redelivery_guard(self.id, rtt + CLIENT_CYCLE);
            let released = core.sched.release_deferred(self.id, Instant::now());
            (core.sched.stats(self.id), released)
        };
        if released > 0 {
            self.shared.wake.notify_one();
        }
        if let Some(st) = stats {
            self.shared.state.update_session(self.id.0, |s| {
                s.queue_depth = st.queue_depth as u64;
                s.in_flight = st.in_flight as u64;
            });
        }
        None
    }

    /// The window from quinn's RTT and congestion window; returns the RTT.
    fn update_window(&mut self) -> Duration {
        let config = &self.shared.config;
        // One look at the connection's state (its lock is the one quinn's driver sends under).
        let path = self.conn.stats().path;
        let (rtt, cwnd) = (path.rtt, path.cwnd);
        // Twice the congestion window per round trip: a connection kept within its window is
        // application-limited, and QUIC's slow start then never grows the window (measured:
        // 10–40 treelets per 50 ms round trip on a 100 Mbit/s link that carries 600).
        let bandwidth = 2.0 * cwnd as f64 / rtt.as_secs_f64().max(1e-6);
        let w = window_for(
            bandwidth,
            rtt,
            self.ctx.mean_treelet_bytes() as usize,
            config.window_min,
            config.window_max,
        );
        if w != self.window {
            let _ = self.shared.core().sched.set_window(self.id, w);
            tracing::trace!(window = w, rtt_us = rtt.as_micros() as u64, cwnd, "window");
            self.window = w;
            self.shared.wake.notify_one();
        }
        rtt
    }

    /// Shutdown of one connection: stop taking lists, let in-flight streams finish until the
    /// deadline, reset the rest, then say goodbye.
    async fn drain(&mut self, deadline: Instant) -> End {
        // Treelets handed over but not started are not started now.
        {
            let mut core = self.shared.core();
            while let Ok(batch) = self.jobs.try_recv() {
                for t in batch {
                    core.sched.handle_cancelled(self.id, t);
                }
            }
        }
        let deadline = tokio::time::Instant::from_std(deadline);
        let in_flight = self.streams.len();
        while !self.streams.is_empty() {
            tokio::select! {
                joined = self.streams.join_next() => {
                    if let Some(Ok((id, batch, outcome))) = joined {
                        self.on_stream_end(id, &batch, outcome);
                    }
                }
                _ = tokio::time::sleep_until(deadline) => break,
            }
        }
        let left = self.streams.len();
        for tx in self.batches.drain() {
            let _ = tx.send(ErrorCode::ShuttingDown);
        }
        tracing::debug!(in_flight, reset = left, "drained for shutdown");
        End::Close {
            code: ErrorCode::ShuttingDown,
            reason: "server shutting down".into(),
            goodbye: true,
        }
    }

    /// Whatever is still in flight ends with the connection.
    async fn finish(&mut self, end: &End) {
        let code = match end {
            End::Close { code, .. } => *code,
            End::Lost(_) => CANCEL_CODE,
        };
        for tx in self.batches.drain() {
            let _ = tx.send(code);
        }
        let streams = &mut self.streams;
        let _ = tokio::time::timeout(Duration::from_millis(100), async {
            while streams.join_next().await.is_some() {}
        })
        .await;
        self.streams.abort_all();
        self.opener.0.abort();
    }
}

/// Aborts a task when dropped.
struct AbortOnDrop<T>(tokio::task::JoinHandle<T>);

impl<T> Drop for AbortOnDrop<T> {
    fn drop(&mut self) {
        self.0.abort();
    }
}

/// Waits for the plan being made on a reader (`None` never completes: the `select!` branch is
/// disabled then), and clears the job.
async fn join_plan(
    job: &mut Option<AbortOnDrop<Option<PlannedOnReader>>>,
) -> Option<PlannedOnReader> {
    let Some(running) = job.as_mut() else {
        return std::future::pending().await;
    };
    let planned = (&mut running.0).await.ok().flatten();
    *job = None;
    planned
}

/// Waits for the visible cut being computed (`None` never completes: the `select!` branch is
/// disabled then), and clears the job.
async fn join_cut(
    job: &mut Option<tokio::task::JoinHandle<Option<(VisibleCut, bool)>>>,
) -> Result<Option<(VisibleCut, bool)>, tokio::task::JoinError> {
    let Some(handle) = job.as_mut() else {
        return std::future::pending().await;
    };
    let result = handle.await;
    *job = None;
    result
}
