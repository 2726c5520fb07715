//! Chaining windows into map segments.

use crate::map::{MapBuilder, PointPair, WindowInput, WindowOutcome};
use crate::window_alignment::transform_pose;
use egoslam_geometry::StampedPose;

impl MapBuilder {
    /// Adds a solved window: aligned on the keyframes it shares with the current segment,
    /// or a new segment when it shares fewer than two.
    pub fn add_window(&mut self, window: &WindowInput) -> WindowOutcome {
        self.add_window_with_scale(window, None)
    }

    /// Whether `window` would be chained onto the current segment without shared points
    /// that can give its scale ([`Self::weakly_joined`]): then a scale measured otherwise
    /// ([`crate::relocalized_scale`]) is worth the cost.
    pub fn lacks_shared_points(&self, window: &WindowInput) -> bool {
        let Some(segment) = self.current_segment else {
            return false;
        };
        let (keyframes, points) = self.shared_with(window, segment);
        keyframes.len() >= 2 && self.weakly_joined(segment, window, points.len())
    }

    /// What `window` shares with `segment`: `(window pose, map pose)` of each keyframe and
    /// `(window position, map position)` of each point.
    fn shared_with(
        &self,
        window: &WindowInput,
        segment: u32,
    ) -> (Vec<(StampedPose, StampedPose)>, Vec<PointPair>) {
        let keyframes = window
            .poses
            .iter()
            .filter_map(|(id, p)| match self.keyframes.get(id) {
                Some((s, m)) if *s == segment => Some((*p, *m)),
                _ => None,
            })
            .collect();
        let points = self
            .shared_points(window, segment)
            .map(|(_, pair)| pair)
            .collect();
        (keyframes, points)
    }

    /// The points `window` shares with `segment`: track id, `(window position, map
    /// position)`.
    pub(crate) fn shared_points<'a>(
        &'a self,
        window: &'a WindowInput,
        segment: u32,
    ) -> impl Iterator<Item = (u64, PointPair)> + 'a {
        window
            .points
            .iter()
            .filter_map(move |(track, x)| match self.points.get(track) {
                Some((s, xm)) if *s == segment => Some((*track, (*x, *xm))),
                _ => None,
            })
    }

    /// [`Self::add_window`]; when too few points are shared, `relocalized_scale` (if any)
    /// gives the scale before the walking pace and the scene-depth ratio are tried
    /// ([`Self::chaining_transform`]).
    pub fn add_window_with_scale(
        &mut self,
        window: &WindowInput,
        relocalized_scale: Option<crate::RelocalizedScale>,
    ) -> WindowOutcome {
        let first_new = window
            .poses
            .iter()
            .position(|(id, _)| {
                !matches!(self.keyframes.get(id), Some((s, _)) if Some(*s) == self.current_segment)
            })
            .unwrap_or(window.poses.len());
        let options = crate::interior_cut::InteriorCutOptions::default();
        let rescaled = crate::interior_cut::rescale_after_weak_cut(window, first_new, &options);
        let window = match &rescaled {
            Some((rescaled, cut, scale)) => {
                tracing::info!(
                    after_keyframe = window.poses[cut.after].0,
                    transfer_points = cut.transfer_points,
                    scale,
                    "cut inside the window (weak, or the pace jumps across it): the keyframes after it take the pace before"
                );
                rescaled
            }
            None => window,
        };
        let shared = self
            .current_segment
            .map(|seg| (seg, self.shared_with(window, seg)));
        let (segment, transform, outcome) = match shared {
            Some((seg, (shared, shared_points))) if shared.len() >= 2 => {
                let (w, m): (Vec<_>, Vec<_>) = shared.into_iter().unzip();
                let (transform, residual, scale_source) = self.chaining_transform(
                    seg,
                    window,
                    (&w, &m),
                    &shared_points,
                    relocalized_scale,
                );
                tracing::debug!(
                    first_keyframe = window.poses.first().map(|(id, _)| *id),
                    shared_points = shared_points.len(),
                    ?scale_source,
                    scale = transform.scale,
                    "window scale"
                );
                if let Some((id, _)) = window.poses.get(first_new) {
                    self.note_chaining_scale(seg, *id, scale_source);
                }
                (
                    seg,
                    transform,
                    WindowOutcome::Aligned {
                        segment: seg,
                        transform,
                        residual,
                        scale_source,
                    },
                )
            }
            _ => {
                let seg = self.segments;
                self.segments += 1;
                self.current_segment = Some(seg);
                (
                    seg,
                    crate::speed_continuity::new_segment_gauge(window),
                    WindowOutcome::NewSegment { segment: seg },
                )
            }
        };
        for (id, p) in &window.poses {
            // Keyframes already in this segment keep their pose (the older window anchored
            // them); new ones are added in the segment's frame.
            let keep = matches!(self.keyframes.get(id), Some((s, _)) if *s == segment);
            if !keep {
                self.keyframes
                    .insert(*id, (segment, transform_pose(&transform, p)));
            }
        }
        for (track, x) in &window.points {
            // Points already in the map keep their (refined) position; new ones come in.
            let known = matches!(self.points.get(track), Some((s, _)) if *s == segment);
            if !known {
                self.points.insert(*track, (segment, transform.apply(x)));
            }
        }
        for (kf, track, px) in &window.observations {
            self.observations.insert((*kf, *track), *px);
            // Triangulated now: what was kept of it as weak joins its observations.
            if let Some(views) = self.weak.remove(track) {
                for (k, p) in views {
                    self.observations.entry((k, *track)).or_insert(p);
                }
            }
        }
        self.add_weak_observations(&window.weak_observations);
        outcome
    }
}

#[cfg(test)]
mod tests;
