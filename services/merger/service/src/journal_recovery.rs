//! How a restarted merger recovers the windows it missed from the solver's journal
//! (docs/durability.md, "What a restarted merger does").

use super::Merger;
use anyhow::{bail, Context};
use egoslam_durability::window_journal;

impl Merger {
    /// Applies the journal's messages from the next expected one up to (not including)
    /// `until` (all of them when `None`). With `until` set, the journal must hold them: a
    /// gap that cannot be filled is an error, never a silent loss.
    pub(super) fn catch_up(&mut self, until: Option<(u64, u64)>) -> anyhow::Result<()> {
        let path = egoslam_durability::state_dir(&self.options.out).join(window_journal::FILE_NAME);
        let journal = match window_journal::read(&path) {
            Ok(j) => Some(j),
            Err(e) if until.is_none() => {
                tracing::warn!(error = %e, "no journal to resume from");
                None
            }
            Err(e) => return Err(e.into()),
        };
        let wanted_stream = until
            .map(|(_, stream)| stream)
            .or(self.session.state.stream_id);
        let Some(journal) = journal.filter(|j| Some(j.stream_id) == wanted_stream) else {
            if let Some((sequence, _)) = until {
                bail!(
                    "windows {}..{sequence} were missed and {} does not hold them",
                    self.session.state.next_sequence(),
                    path.display()
                );
            }
            return Ok(());
        };
        self.begin_stream(journal.stream_id)?;
        let first = self.session.state.next_sequence();
        let last = until.map_or(journal.next_sequence(), |(s, _)| s);
        if last > journal.next_sequence() || (first < last && first < journal.first_sequence) {
            bail!(
                "windows {first}..{last} were missed and {} holds only {}..{}",
                path.display(),
                journal.first_sequence,
                journal.next_sequence()
            );
        }
        if first < last {
            tracing::info!(first, last, "recovering windows from the journal");
            self.stats.count("recovered_windows", last - first);
        }
        for sequence in first..last {
            let message = journal
                .message(sequence)
                .with_context(|| format!("{}: no window {sequence}", path.display()))?;
            self.apply(sequence, message)?;
        }
        Ok(())
    }
}
