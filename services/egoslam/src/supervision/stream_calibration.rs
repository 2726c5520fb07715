//! The self-calibrations of a recorded input made from the stream instead of before it.
//!
//! `egoslam run` used to track a recording's first frames (and solve their first windows)
//! before starting the services, to estimate the rolling-shutter readout (`auto`) and the
//! radial or focal correction (`--calibrate-radial`, `--calibrate-focal`): a pass that
//! blocked the start for 1.8 s of the rendered 10 s walk's 5.4 s. Now the services start at
//! once with the calibration as given. The frontend estimates the readout from the first
//! frames it tracks anyway and holds their keyframes until then, correcting them with the
//! estimate (readout_hold.rs, as on a live stream; a global shutter is decided early,
//! `EarlyGlobalShutter`), so a readout never starts the run again. The solver estimates
//! the intrinsics from the first keyframes it receives (`--estimate-intrinsics`). Most
//! inputs need no intrinsic correction, and their run is the one a pre-pass would have
//! started. When one applies, the run starts again from the input's first frame with it,
//! so that every process and the saved camera use it from the start: the final results
//! are those of a run told the estimate, at the cost of the frames processed before it
//! came (300 frames). The estimates are made in this order, as the pre-pass made them:
//! the readout, then the focal length, then the radial term, each on the camera corrected
//! by the ones before.

use crate::calibration::focal::{scaled, with_radial};
use crate::calibration::settings::Readout;
use egoslam_geometry::PinholeRadtan;
use egoslam_solver_service::intrinsics_estimation::FILE_NAME as INTRINSICS_FILE;
use serde_json::json;
use std::path::Path;

/// Where an estimate stands.
#[derive(Debug, Clone, PartialEq)]
enum Estimate {
    /// Not asked for (a setting, or a live camera).
    Off(serde_json::Value),
    /// Asked of the services of this round.
    Asked,
    /// Final: the report's figures.
    Done(serde_json::Value),
}

/// The stream's self-calibrations over the rounds of a run.
pub struct StreamCalibration {
    readout: Estimate,
    focal: Estimate,
    radial: Estimate,
    /// The readout the frontend estimated, ms, once it has.
    readout_ms: Option<f64>,
    /// Rounds started again for an estimate.
    pub restarts: u32,
}

/// What the services of the next round are told.
pub struct RoundSettings {
    pub readout: Readout,
    pub camera: PinholeRadtan,
}

impl StreamCalibration {
    /// A live camera's: nothing is estimated here (the frontend holds its keyframes for
    /// an `auto` readout; the intrinsics stay as calibrated).
    pub fn live(readout: Readout) -> Self {
        let off = || {
            Estimate::Off(json!({ "setting": true, "error": "a live camera cannot be read ahead" }))
        };
        let readout = match readout {
            Readout::Auto => {
                Estimate::Off(json!({ "setting": "auto", "estimated_by": "the frontend, online" }))
            }
            Readout::Millis(ms) => {
                Estimate::Off(json!({ "setting": ms.to_string(), "readout_ms": ms }))
            }
        };
        Self {
            readout,
            focal: off(),
            radial: off(),
            readout_ms: None,
            restarts: 0,
        }
    }

    /// The plan for a recorded input: the readout from the stream when `readout` is
    /// `auto`, focal and radial when asked (`radial`: the setting applies to the camera).
    pub fn new(readout: Readout, focal: bool, radial: bool) -> Self {
        let asked = |on: bool| {
            if on {
                Estimate::Asked
            } else {
                Estimate::Off(json!({ "setting": false }))
            }
        };
        let readout = match readout {
            Readout::Auto => Estimate::Asked,
            Readout::Millis(ms) => {
                Estimate::Off(json!({ "setting": ms.to_string(), "readout_ms": ms }))
            }
        };
        Self {
            readout,
            focal: asked(focal),
            radial: asked(radial),
            readout_ms: None,
            restarts: 0,
        }
    }

    /// The services' flags for this round: the first revision of a round started again,
    /// and the intrinsics the solver estimates (in the same round as the readout, on the
    /// keyframes the frontend corrected with it).
    pub fn flags(&self) -> Vec<String> {
        let mut flags = Vec::new();
        if self.restarts > 0 {
            flags.push(format!(
                "--first-revision={}",
                self.restarts << egoslam_messages::ROUND_REVISION_BITS
            ));
        }
        let asked: Vec<&str> = [("focal", &self.focal), ("radial", &self.radial)]
            .into_iter()
            .filter(|(_, e)| **e == Estimate::Asked)
            .map(|(name, _)| name)
            .collect();
        if !asked.is_empty() {
            flags.push(format!("--estimate-intrinsics={}", asked.join(",")));
        }
        flags
    }

    /// Reads what the round's services in `out` estimated so far; `Some` with the next
    /// round's settings when the run must start again with an estimate (`current`: this
    /// round's).
    pub fn check(&mut self, out: &Path, current: &RoundSettings) -> Option<RoundSettings> {
        if self.readout == Estimate::Asked {
            let ms = egoslam_durability::estimated_readout::read(out)?;
            self.readout_ms = Some(ms);
            let details = std::fs::read_to_string(
                egoslam_durability::state_dir(out)
                    .join(egoslam_frontend_service::online_readout::DETAILS_FILE),
            )
            .ok()
            .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok());
            self.readout = Estimate::Done(json!({
                "setting": "auto",
                "readout_ms": ms,
                "estimate": details,
                "estimated_by": "the frontend, from the stream's first frames (their keyframes held and corrected)",
            }));
        }
        if self.focal != Estimate::Asked && self.radial != Estimate::Asked {
            return None;
        }
        let text =
            std::fs::read_to_string(egoslam_durability::state_dir(out).join(INTRINSICS_FILE))
                .ok()?;
        let estimates: serde_json::Value = serde_json::from_str(&text).ok()?;
        let tag = |mut v: serde_json::Value| {
            v["setting"] = json!(true);
            v["estimated_by"] = json!("the solver, from the stream's first windows");
            v
        };
        if self.focal == Estimate::Asked {
            let focal = tag(estimates["focal"].clone());
            let scale = focal["applied_scale"].as_f64().unwrap_or(1.0);
            self.focal = Estimate::Done(focal);
            if scale != 1.0 {
                // The radial term is estimated again on the corrected focal length.
                tracing::info!(scale, "a focal correction: the run starts again with it");
                return Some(RoundSettings {
                    readout: self.decided_readout(current),
                    camera: scaled(&current.camera, scale),
                });
            }
        }
        if self.radial == Estimate::Asked {
            let radial = tag(estimates["radial"].clone());
            let k = radial["applied_k"].as_f64().unwrap_or(0.0);
            self.radial = Estimate::Done(radial);
            if k != 0.0 {
                tracing::info!(k, "a radial term: the run starts again with it");
                return Some(RoundSettings {
                    readout: self.decided_readout(current),
                    camera: with_radial(&current.camera, k),
                });
            }
        }
        None
    }

    /// The readout of the rounds after this one: the estimate once made.
    fn decided_readout(&self, current: &RoundSettings) -> Readout {
        self.readout_ms.map_or(current.readout, Readout::Millis)
    }

    /// Counts a round started again (its services number their poses above the last's).
    pub fn start_again(&mut self) {
        self.restarts += 1;
    }

    /// The report's rolling_shutter, focal_calibration and radial_calibration entries.
    pub fn reports(&self) -> [serde_json::Value; 3] {
        let report = |e: &Estimate| match e {
            Estimate::Off(v) | Estimate::Done(v) => v.clone(),
            Estimate::Asked => {
                json!({ "setting": true, "error": "the stream ended before an estimate" })
            }
        };
        [
            report(&self.readout),
            report(&self.focal),
            report(&self.radial),
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera() -> PinholeRadtan {
        PinholeRadtan::new(640, 480, [500.0, 500.0, 320.0, 240.0], [0.0; 5]).expect("camera")
    }

    fn write_intrinsics(out: &Path, estimates: serde_json::Value) {
        let path = egoslam_durability::state_dir(out).join(INTRINSICS_FILE);
        std::fs::create_dir_all(path.parent().expect("state dir")).expect("state dir");
        std::fs::write(path, estimates.to_string()).expect("written");
    }

    /// The estimates are taken in the order they depend on each other: the intrinsics
    /// wait for the readout (the frontend holds its keyframes for it, so it never starts
    /// the run again); a focal correction starts the run again, told the readout, and
    /// asks the radial term again; nothing found ends the rounds.
    #[test]
    fn a_run_starts_again_for_each_intrinsic_that_applies_in_order() {
        let out = tempfile::tempdir().expect("tempdir");
        let out = out.path();
        let mut plan = StreamCalibration::new(Readout::Auto, true, true);
        let mut round = RoundSettings {
            readout: Readout::Auto,
            camera: camera(),
        };
        assert_eq!(plan.flags(), vec!["--estimate-intrinsics=focal,radial"]);
        // Nothing estimated yet.
        assert!(plan.check(out, &round).is_none());
        // The intrinsics come first but wait for the readout.
        write_intrinsics(
            out,
            json!({ "focal": { "applied_scale": 0.97 }, "radial": { "applied_k": 0.0 } }),
        );
        assert!(plan.check(out, &round).is_none());
        egoslam_durability::estimated_readout::write(out, 21.0).expect("readout");
        let next = plan.check(out, &round).expect("again for the focal length");
        assert_eq!(next.readout, Readout::Millis(21.0));
        assert!((next.camera.fx - 485.0).abs() < 1e-9);
        assert_eq!(
            next.camera.distortion[0], 0.0,
            "the radial term is asked again"
        );
        plan.start_again();
        round = next;
        let _ = std::fs::remove_dir_all(egoslam_durability::state_dir(out));
        assert_eq!(
            plan.flags(),
            vec!["--first-revision=16777216", "--estimate-intrinsics=radial"]
        );
        write_intrinsics(
            out,
            json!({ "focal": null, "radial": { "applied_k": 0.0, "k": 0.001 } }),
        );
        assert!(plan.check(out, &round).is_none(), "nothing more applies");
        let [readout, focal, radial] = plan.reports();
        assert_eq!(readout["readout_ms"], 21.0);
        assert_eq!(focal["applied_scale"], 0.97);
        assert_eq!(radial["applied_k"], 0.0);
        assert_eq!(plan.restarts, 1);
    }

    /// A readout found never starts the run again: the frontend held its keyframes.
    #[test]
    fn a_readout_never_starts_the_run_again() {
        let out = tempfile::tempdir().expect("tempdir");
        let out = out.path();
        let mut plan = StreamCalibration::new(Readout::Auto, false, false);
        let round = RoundSettings {
            readout: Readout::Auto,
            camera: camera(),
        };
        assert!(plan.flags().is_empty(), "the frontend holds");
        egoslam_durability::estimated_readout::write(out, 21.0).expect("readout");
        assert!(plan.check(out, &round).is_none());
        assert_eq!(plan.reports()[0]["readout_ms"], 21.0);
        assert_eq!(plan.restarts, 0);
    }

    /// A global shutter and nothing to correct: the first round is the run.
    #[test]
    fn nothing_found_never_starts_the_run_again() {
        let out = tempfile::tempdir().expect("tempdir");
        let out = out.path();
        let mut plan = StreamCalibration::new(Readout::Auto, false, true);
        let round = RoundSettings {
            readout: Readout::Auto,
            camera: camera(),
        };
        egoslam_durability::estimated_readout::write(out, 0.0).expect("readout");
        assert!(plan.check(out, &round).is_none());
        write_intrinsics(
            out,
            json!({ "focal": null, "radial": { "applied_k": 0.0 } }),
        );
        assert!(plan.check(out, &round).is_none());
        assert_eq!(plan.restarts, 0);
        assert_eq!(plan.reports()[1]["setting"], false);
    }
}
