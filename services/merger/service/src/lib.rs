//! The merger service: window solutions from the bus -> one map -> result files and zenoh.
//! A thin loop around egoslam_merger's [`MergerSession`]: receive a window (or read it back
//! from the solver's journal), apply it, publish, persist.
//!
//! After every window the state is checkpointed and the files rewritten (atomically); a
//! killed merger restarts from its checkpoint and recovers the windows it had not applied
//! from the solver's journal, so nothing is lost (docs/durability.md). The same state goes
//! out over zenoh (docs/egress.md).

mod journal_recovery;
mod live_tracking;
mod map_state;
mod outputs;
mod saved_map;
use anyhow::bail;
use egoslam_bus::{Bus, BusOptions, MessageSubscriber, WINDOWS};
use egoslam_durability::checkpoint::{self, Checkpoint};
use egoslam_durability::features_log::{patched_tracks, FeaturesLog, Keep, PENDING_LIMIT_BYTES};
use egoslam_durability::log_compaction;
use egoslam_egress::{Egress, EgressOptions};
use egoslam_merger::session::frames::{posed_frames, posed_keyframes};
use egoslam_merger::session::Tally;
use egoslam_merger::{
    MergerSession, MergerState, PointConfidenceOptions, SessionOptions, StreamStart,
};
use egoslam_messages::internal::v1 as internal;
use egoslam_messages::v1 as pb;
use egoslam_relocalization::saved_map::{features_from_pb, patches_from_pb};
use egoslam_runtime::ServiceStats;
use map_state::{PublishedPoints, Revisions};
use outputs::Outputs;
use std::collections::VecDeque;
use std::path::PathBuf;

/// What a merger service is told (the launcher's `egoslam merger` flags, docs/config.md).
#[derive(Debug, Clone)]
pub struct MergerServiceOptions {
    /// Bus namespace (iceoryx2 service names egoslam/<namespace>/...).
    pub namespace: String,
    /// The revision of a frame's first published pose (`Revisions::starting_at`: above
    /// an earlier round's when the run started again).
    pub first_revision: u32,
    /// Output folder: result files, statistics, and the state folder (checkpoint, journal).
    pub out: PathBuf,
    /// A saved map this run extends.
    pub map_in: Option<PathBuf>,
    /// Where the map is saved at the end of the stream, for relocalization.
    pub map_out: Option<PathBuf>,
    /// Vocabulary file (None: the built-in one).
    pub vocabulary: Option<PathBuf>,
    /// How results go out over zenoh (None: not at all).
    pub egress: Option<EgressOptions>,
    /// The map's refinement, loop closure and culling.
    pub session: SessionOptions,
    /// Points published and written only below this relative standard deviation.
    pub max_point_std: f64,
    /// Also write every point, however uncertain (map_all.ply).
    pub map_all_points: bool,
    /// Frames this much stream time older than the newest are final: out of memory and
    /// the checkpoint, their rows frozen in trajectory.tum (infinite: never).
    pub frame_horizon_s: f64,
    /// The rolling-shutter readout the frames were corrected for, saved with the map: given
    /// (ms), or None when the frontend estimates it online (read from its state file).
    pub rolling_shutter_ms: Option<f64>,
}

/// The merger at work: its durable state, where it writes, what it publishes.
struct Merger {
    options: MergerServiceOptions,
    /// The map and everything about it (egoslam_merger::session).
    session: MergerSession,
    outputs: Outputs,
    stats: ServiceStats,
    /// When the files and checkpoint were last written.
    last_persist: Option<std::time::Instant>,
    /// Time the next rewrite waits for (`persist_due`).
    persist_spacing: std::time::Duration,
    /// Where keyframe descriptors are persisted (not in the checkpoint); the session reads
    /// them back for loop closure, linking and culling.
    features_log: FeaturesLog,
    /// Poses every frame as it arrives (revision 0); handed the map after each window.
    live: Option<live_tracking::LiveTracking>,
}

/// Shortest time between rewrites of the result files and the checkpoint. Rewriting both
/// after every window made a 12,000-frame walk spend 370 of its 428 s there (they grow
/// with the map); the journal makes waiting safe.
const PERSIST_INTERVAL: std::time::Duration = std::time::Duration::from_secs(5);

/// Average bytes per second the rewrites of the checkpoint and the result files may write
/// (512 KiB/s, 1.8 GiB per hour): a rewrite waits, beyond [`PERSIST_INTERVAL`], as long as
/// the last one's size takes at that rate. The checkpoint is the whole map and
/// trajectory.tum every frame of the run (9.1 MB after the hour-long endurance run, and it
/// grows linearly with the frames): rewritten every 5 s they would write more each hour than the last, flash wear that
/// would end a wearable's storage within months. Windows in between stay in the solver's
/// journal.
/// `EGOSLAM_PERSIST_BUDGET_BYTES_PER_S` sets another rate ("inf": every 5 s).
const PERSIST_BUDGET_BYTES_PER_S: f64 = 512.0 * 1024.0;

fn persist_budget() -> f64 {
    positive_from_env("EGOSLAM_PERSIST_BUDGET_BYTES_PER_S").unwrap_or(PERSIST_BUDGET_BYTES_PER_S)
}

/// The positive number environment variable `name` gives, if any.
fn positive_from_env<T: std::str::FromStr + PartialOrd + Default>(name: &str) -> Option<T> {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse::<T>().ok())
        .filter(|n| *n > T::default())
}

/// What the features log keeps of a keyframe's record: a map keyframe's whole (without
/// its patches past retention), a culled one's patched tracks, nothing of the rest.
fn keep_of(session: &MergerSession) -> impl Fn(u64) -> Keep + '_ {
    let (map, patched) = (&session.state.map, &session.state.patched_tracks);
    move |keyframe: u64| {
        if map.keyframe(keyframe).is_some() {
            if session.patches_expired(keyframe) {
                Keep::Features
            } else {
                Keep::Whole
            }
        } else if let Some(tracks) = patched.get(&keyframe) {
            Keep::Tracks(tracks.iter().map(|(t, _)| *t).collect())
        } else {
            Keep::Nothing
        }
    }
}

impl Merger {
    fn checkpoint_path(&self) -> std::path::PathBuf {
        egoslam_durability::state_dir(&self.options.out).join(checkpoint::FILE_NAME)
    }

    /// Makes `stream_id` the current solver stream (`MergerSession::begin_stream`); a new
    /// map empties the features log and starts from the saved map to extend, if any.
    fn begin_stream(&mut self, stream_id: u64) -> anyhow::Result<()> {
        if self.session.begin_stream(stream_id) == StreamStart::NewMap {
            self.features_log.truncate()?;
            if let Some(path) = self.options.map_in.clone() {
                self.extend_saved_map(&path)?;
            }
        }
        Ok(())
    }

    /// Adds the session's timings and counters to the service's statistics.
    fn take_tally(&mut self) {
        let Tally {
            timings_ms,
            counters,
        } = self.session.tally.take();
        self.stats.absorb(ServiceStats {
            timings_ms,
            counters,
            ..ServiceStats::default()
        });
    }

    /// Applies message `sequence`, checkpoints, and writes/publishes the results.
    fn apply(&mut self, sequence: u64, w: &internal::WindowSolution) -> anyhow::Result<()> {
        self.begin_stream(w.stream_id)?;
        for f in &w.keyframe_features {
            match features_from_pb(f).zip(patches_from_pb(f)) {
                Some((features, patches)) => {
                    let patched = patched_tracks(&patches);
                    self.session.add_keyframe(f.keyframe_id, &features, patched);
                    self.features_log.append(f);
                }
                None => {
                    tracing::warn!(
                        keyframe = f.keyframe_id,
                        "inconsistent keyframe descriptors ignored"
                    );
                    self.stats.count("invalid_features", 1);
                }
            }
        }
        self.session.apply_window(sequence, w, &self.features_log);
        self.take_tally();
        // Records older than the pending limit are written now, as far as the map still
        // wants them; loop closure and linking read them back from the log.
        let written = self
            .features_log
            .write_pending(keep_of(&self.session), PENDING_LIMIT_BYTES)?;
        self.stats.count("features_log_written_bytes", written);
        self.features_log.flush()?;
        if let Some(live) = &self.live {
            live.update(
                &self.session.state.map,
                self.session.camera(),
                &w.keyframe_ids,
            );
        }
        // Publish first, then checkpoint (with the revisions just published): a kill in
        // between re-applies this window from the journal, which publishes the same again.
        let write_start = std::time::Instant::now();
        let state = if self.session.state.finished {
            pb::ServiceState::Finished
        } else {
            pb::ServiceState::Running
        };
        let persist = self.persist_due();
        let result_bytes = self.emit(state, persist)?;
        self.stats
            .add_time("write", write_start.elapsed().as_secs_f64() * 1e3);
        if persist {
            self.persist(result_bytes)?;
        }
        Ok(())
    }

    /// Checkpoints the session's state (with the revisions published), compacting the
    /// features log when due, and tells the solver what its journal may drop;
    /// `result_bytes` is what the result files just written took, counted with the
    /// checkpoint against the write budget.
    fn persist(&mut self, result_bytes: u64) -> anyhow::Result<()> {
        self.session.state.revisions = self
            .outputs
            .revisions
            .lock()
            .map_err(|_| anyhow::anyhow!("revisions poisoned"))?
            .numbers();
        let save_start = std::time::Instant::now();
        self.session.prune_culled_patches();
        let keep = keep_of(&self.session);
        let written = self.features_log.write_pending(&keep, 0)?;
        self.stats.count("features_log_written_bytes", written);
        if self.features_log.compact_if_due(&keep)? > 0 {
            self.stats.count("features_log_compactions", 1);
        }
        self.features_log.sync()?;
        self.session.state.save(&self.checkpoint_path())?;
        // The solver may now drop the journal's records before the next one.
        if let Some(stream) = self.session.state.stream_id {
            log_compaction::write_mark(
                &egoslam_durability::state_dir(&self.options.out).join(log_compaction::MERGER_MARK),
                stream,
                self.session.state.next_sequence(),
            )?;
        }
        self.stats
            .add_time("checkpoint", save_start.elapsed().as_secs_f64() * 1e3);
        self.last_persist = Some(std::time::Instant::now());
        let bytes = result_bytes + std::fs::metadata(self.checkpoint_path()).map_or(0, |m| m.len());
        self.persist_spacing = PERSIST_INTERVAL.max(
            std::time::Duration::try_from_secs_f64(bytes as f64 / persist_budget())
                .unwrap_or(PERSIST_INTERVAL),
        );
        self.stats.count("checkpoints", 1);
        // The serialization buffer and anything a folded refinement freed since.
        egoslam_runtime::memory::return_freed_memory();
        Ok(())
    }

    /// Publishes over zenoh; with `persist`, also rewrites the result files (returns the
    /// bytes written).
    fn emit(&mut self, state: pb::ServiceState, persist: bool) -> anyhow::Result<u64> {
        self.stats.windows = self.session.state.windows;
        self.stats.counters.insert(
            "unsolved_windows".into(),
            self.session.state.unsolved_windows,
        );
        let camera = self.session.camera().cloned();
        self.outputs.emit(
            &self.options.out,
            &mut self.session.state,
            camera.as_ref(),
            state,
            &mut self.stats,
            persist,
        )
    }

    /// Whether the files and the checkpoint are due: at most every
    /// [`PERSIST_INTERVAL`] or as the write budget allows ([`PERSIST_BUDGET_BYTES_PER_S`]),
    /// and always at the end of the stream. Windows in between are safe in the solver's
    /// journal, from which a restarted merger replays them.
    fn persist_due(&self) -> bool {
        self.session.state.finished
            || self
                .last_persist
                .is_none_or(|t| t.elapsed() >= self.persist_spacing)
    }
}

/// Windows a merger holds in memory while it is behind the solver, at most
/// [`BACKLOG_WINDOWS`] (~1 MB each on a head-mounted walk; unbounded, a merger behind by
/// minutes held ~500 MB of them). Beyond that a window is dropped from memory: the
/// solver journaled it before sending it, and the merger reads it back from the journal
/// when its turn comes (`window_journal::read_one`). The end of a stream and a new
/// stream's windows are always kept.
struct Backlog {
    windows: VecDeque<(u64, internal::WindowSolution)>,
    capacity: usize,
    /// The newest window of the current stream left in the journal.
    left_in_journal: Option<u64>,
}

/// Windows held in memory at most (`EGOSLAM_MERGER_BACKLOG_WINDOWS` sets another number,
/// at least 1).
const BACKLOG_WINDOWS: usize = 16;

fn backlog_windows() -> usize {
    positive_from_env("EGOSLAM_MERGER_BACKLOG_WINDOWS").unwrap_or(BACKLOG_WINDOWS)
}

impl Backlog {
    fn new(capacity: usize) -> Self {
        Self {
            windows: VecDeque::new(),
            capacity,
            left_in_journal: None,
        }
    }

    /// Keeps window `next` (of the merger's `stream`) in memory, or leaves it in the
    /// journal when the backlog is full (false).
    fn take(&mut self, next: (u64, internal::WindowSolution), stream: Option<u64>) -> bool {
        let (sequence, w) = &next;
        let same_stream = stream == Some(w.stream_id);
        if self.windows.len() < self.capacity || w.end_of_stream || !same_stream {
            self.windows.push_back(next);
            return true;
        }
        self.left_in_journal = Some(self.left_in_journal.map_or(*sequence, |s| s.max(*sequence)));
        false
    }

    /// Nothing to apply: no window in memory and none of `stream` left in the journal
    /// from sequence number `next` on.
    fn is_empty(&self, stream: Option<u64>, next: u64) -> bool {
        self.windows.is_empty()
            && (stream.is_none() || self.left_in_journal.is_none_or(|last| last < next))
    }

    fn front(&self) -> Option<&(u64, internal::WindowSolution)> {
        self.windows.front()
    }

    fn pop_front(&mut self) -> Option<(u64, internal::WindowSolution)> {
        self.windows.pop_front()
    }
}

fn open_egress(options: Option<&EgressOptions>) -> anyhow::Result<Option<Egress>> {
    let Some(options) = options else {
        return Ok(None);
    };
    let e = Egress::open(options)?;
    tracing::info!(prefix = e.prefix(), listen = ?options.network.listen, "publishing over zenoh");
    Ok(Some(e))
}

/// Fault injection for the durability tests (docs/durability.md):
/// `EGOSLAM_FAULT=merger-abort-at-window:N` makes a merger that did not resume from a
/// checkpoint abort as soon as it has received message N, before applying it, i.e. with a
/// window in flight. Only the first merger of a run obeys it (a restarted one resumes).
fn injected_fault() -> Option<u64> {
    let spec = std::env::var("EGOSLAM_FAULT").ok()?;
    let n = spec.strip_prefix("merger-abort-at-window:")?.parse().ok();
    if n.is_none() {
        tracing::warn!(%spec, "EGOSLAM_FAULT not understood; ignored");
    }
    n
}

/// This run's id: the launcher's (`EGOSLAM_RUN_ID`, inherited), else the namespace and this
/// merger's start time, so that a restarted unit keeps no stale id of a run long gone.
fn run_id(namespace: &str) -> String {
    std::env::var("EGOSLAM_RUN_ID").unwrap_or_else(|_| {
        let started = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_millis());
        format!("{namespace}-{started}")
    })
}

/// Runs the merger service until the stream's end (or a signal: an error).
pub fn run(options: MergerServiceOptions) -> anyhow::Result<()> {
    let first_revision = options.first_revision;
    std::fs::create_dir_all(&options.out)?;
    let state_dir = egoslam_durability::create_state_dir(&options.out)?;
    let checkpoint_path = state_dir.join(checkpoint::FILE_NAME);
    let resumed = MergerState::load(&checkpoint_path)?;
    let bus = Bus::open(
        "merger",
        BusOptions {
            namespace: options.namespace.clone(),
            ..BusOptions::default()
        },
    )?;
    let outputs = Outputs {
        egress: open_egress(options.egress.as_ref())?.map(std::sync::Arc::new),
        revisions: std::sync::Arc::new(std::sync::Mutex::new(Revisions::starting_at(
            options.first_revision,
        ))),
        published_points: PublishedPoints::default(),
        frame_poses: Default::default(),
        point_confidence: PointConfidenceOptions {
            max_relative_std: options.max_point_std,
            ..PointConfidenceOptions::default()
        },
        confidence: None,
        run_id: run_id(&options.namespace),
        all_points: options.map_all_points,
        frame_horizon_s: options.frame_horizon_s,
    };
    // Subscribe before reading the journal: whatever the journal does not hold yet is sent
    // after this point and therefore reaches this subscriber.
    let mut windows = MessageSubscriber::<internal::WindowSolution>::create(&bus, WINDOWS)?;
    egoslam_runtime::systemd::ready("merger");
    let vocabulary = egoslam_durability::map_file::load_vocabulary(options.vocabulary.as_deref())?;
    let (features_log, descriptions) = FeaturesLog::open(&state_dir)?;
    let session = MergerSession::new(options.session, vocabulary);
    let mut merger = Merger {
        options,
        session,
        outputs,
        stats: ServiceStats::new("merger"),
        last_persist: None,
        persist_spacing: PERSIST_INTERVAL,
        features_log,
        live: None,
    };
    merger.live = Some(live_tracking::LiveTracking::start(
        &merger.options.namespace,
        &merger.options.out,
        resumed.is_none(),
        live_tracking::Publication {
            egress: merger.outputs.egress.clone(),
            revisions: merger.outputs.revisions.clone(),
            // A saved map to extend puts the new stream in a later segment, known once it
            // is loaded; a restarted merger's stream began long ago.
            origin_segment: (resumed.is_none() && merger.options.map_in.is_none()).then_some(0),
        },
    ));
    let fault = if resumed.is_none() {
        injected_fault()
    } else {
        None
    };
    if let Some(mut state) = resumed {
        tracing::info!(
            windows = state.windows,
            keyframes = state.map.keyframes().count(),
            next = state.next_sequence(),
            finished = state.finished,
            "resuming from the checkpoint"
        );
        merger.stats.count("restarts", 1);
        // Culled keyframes keep only their patches (and those tracks' features).
        state.patched_tracks = descriptions
            .into_iter()
            .filter(|(keyframe, patched)| {
                state.map.keyframe(*keyframe).is_some() || !patched.is_empty()
            })
            .collect();
        let keyframes: Vec<u64> = state.map.keyframes().map(|(id, ..)| id).collect();
        for keyframe in keyframes {
            if let Some(features) = merger.features_log.features_of(keyframe)? {
                merger.session.index_keyframe(keyframe, &features);
            }
        }
        let keyframes = posed_keyframes(&state.map, &state.frames);
        // Below `retired_before`, only keyframes' frames are left (their revisions).
        let resumed_poses = posed_frames(&state.map, &state.frames, &keyframes, ..);
        let retired_before = state.frames.retired_before;
        *merger
            .outputs
            .revisions
            .lock()
            .map_err(|_| anyhow::anyhow!("revisions poisoned"))? = Revisions::resume(
            &state.revisions,
            &resumed_poses,
            retired_before,
            first_revision,
        );
        merger.session.state = state;
        merger.catch_up(None)?;
    }
    // Windows taken off the bus, not applied yet: while the next one waits for the
    // background refinement (`BackgroundRefiner::holds_next_window`) or the merger is
    // behind, it keeps taking them so that the solver's lossless send never times out.
    let mut backlog = Backlog::new(backlog_windows());
    while !merger.session.state.finished {
        let stream = merger.session.state.stream_id;
        if backlog.is_empty(stream, merger.session.state.next_sequence()) {
            let Some(next) = windows.receive_numbered()? else {
                bail!(egoslam_bus::StoppedBySignal { during: "" })
            };
            backlog.take(next, stream);
        }
        while let Some(next) = windows.try_receive_numbered()? {
            if !backlog.take(next, stream) {
                merger.stats.count("windows_left_in_journal", 1);
            }
        }
        let expected = merger.session.state.next_sequence();
        if backlog.left_in_journal.is_some_and(|last| last < expected) {
            backlog.left_in_journal = None;
        }
        let in_memory = backlog
            .front()
            .is_some_and(|(s, w)| *s == expected && Some(w.stream_id) == stream);
        let from_journal = stream.filter(|_| backlog.left_in_journal.is_some() && !in_memory);
        let next_is_window =
            from_journal.is_some() || backlog.front().is_some_and(|(_, w)| !w.end_of_stream);
        if next_is_window && merger.session.holds_next_window() {
            if !bus.idle(std::time::Duration::from_millis(20)) {
                bail!(egoslam_bus::StoppedBySignal { during: "" })
            }
            continue;
        }
        // Windows left in the journal while the backlog was full come first, one at a
        // time, so that the bus keeps being read in between.
        if let Some(stream) = from_journal {
            let path = egoslam_durability::state_dir(&merger.options.out)
                .join(egoslam_durability::window_journal::FILE_NAME);
            let Some(w) = egoslam_durability::window_journal::read_one(&path, stream, expected)?
            else {
                bail!(
                    "window {expected} was left in {} and it no longer holds it",
                    path.display()
                );
            };
            merger.apply(expected, &w)?;
            continue;
        }
        let Some((sequence, w)) = backlog.pop_front() else {
            continue;
        };
        if fault == Some(sequence) {
            tracing::error!(sequence, "EGOSLAM_FAULT: aborting with a window in flight");
            std::process::abort();
        }
        let same_stream = merger.session.state.stream_id == Some(w.stream_id);
        if same_stream && sequence < merger.session.state.next_sequence() {
            continue; // already applied (recovered from the journal)
        }
        let expected = if same_stream {
            merger.session.state.next_sequence()
        } else {
            0
        };
        if sequence > expected {
            merger.catch_up(Some((sequence, w.stream_id)))?;
        }
        merger.apply(sequence, &w)?;
    }
    merger.stats.count("dropped_messages", windows.dropped());
    if let Some(live) = merger.live.take() {
        merger.stats.absorb(live.finish()?);
    }
    merger.emit(pb::ServiceState::Finished, true)?;
    if let Some(path) = &merger.options.map_out {
        let Some(camera) = merger.session.camera() else {
            bail!("no window was received: there is no map to save")
        };
        // `egoslam run` hands the services the readout it estimated; a frontend left to
        // estimate it online (`auto` under systemd) saves it in the shared output folder
        // (0 until it has, or if it gave up).
        let readout_ms = merger
            .options
            .rolling_shutter_ms
            .or_else(|| egoslam_durability::estimated_readout::read(&merger.options.out))
            .unwrap_or(0.0);
        let readout_s = readout_ms / 1000.0;
        let patches = merger
            .features_log
            .patches(merger.session.state.patched_tracks.keys().copied())?;
        let map = egoslam_durability::map_file::relocalization_map(
            &merger.session.state,
            &merger.features_log,
            &patches,
            camera,
            readout_s,
        );
        let source = merger.options.out.display().to_string();
        egoslam_durability::map_file::write_map(path, &map, merger.session.vocabulary(), &source)?;
    }
    tracing::info!(
        windows = merger.session.state.windows,
        segments = merger.session.state.map.segments(),
        "merger finished"
    );
    Ok(())
}
