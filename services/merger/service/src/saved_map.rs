//! Yesterday's map: a run that starts from a saved map extends it (multi-session).

use super::Merger;
use egoslam_durability::features_log::Keep;
use egoslam_relocalization::saved_map::features_to_pb;

impl Merger {
    /// Starts the map from the saved map at `path` (egoslam_merger::base_map): its
    /// keyframes' descriptors go into the features log and the linking index like the
    /// run's own, so that a restarted merger and segment linking have them.
    pub(super) fn extend_saved_map(&mut self, path: &std::path::Path) -> anyhow::Result<()> {
        let map = egoslam_durability::map_file::read_map(path, self.session.vocabulary())?;
        let (keyframes, points) = (map.keyframes.len(), map.points.len());
        for k in egoslam_durability::map_file::extend_state(&mut self.session.state, map) {
            self.features_log
                .append(&features_to_pb(k.keyframe_id, &k.features, &k.patches));
            self.session.index_keyframe(k.keyframe_id, &k.features);
            // Written at once: a saved map's thousands of records would not wait in memory.
            self.features_log.write_pending(|_| Keep::Whole, 0)?;
        }
        self.features_log.flush()?;
        tracing::info!(
            map = %path.display(),
            keyframes,
            points,
            "extending a saved map"
        );
        Ok(())
    }
}
