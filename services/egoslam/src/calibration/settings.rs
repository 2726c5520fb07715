//! The calibration settings of the pipeline's options whose values say how a calibration
//! is estimated: the rolling-shutter readout (`--rolling-shutter-ms`, a time or `auto`) and
//! when the radial term is self-calibrated (`--calibrate-radial`). Parsed from flags, their
//! environment variables and the configuration file alike (`FromStr`).

use egoslam_geometry::PinholeRadtan;

pub use egoslam_durability::estimated_readout::MAX_READOUT_MS;

/// Frames `auto` estimates the readout from (150: 5 s at 30 fps; the frames a recorded
/// input's run is started again after when it finds one). 300 gave the same estimates on
/// every sequence here (rendered 30 ms walks 29-30 ms, the 15 ms shake 16 ms,
/// tum_fr1_rpy's 120 frames 22 ms, 0 on the global-shutter ones) at twice the cost.
pub const AUTO_FRAMES: u32 = 150;

/// The readout the frontend corrects for.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Readout {
    /// Estimated from the video (recorded inputs; see the module doc).
    Auto,
    /// Given, ms from the first row to the last (0: a global shutter).
    Millis(f64),
}

impl Readout {
    /// The readout given, ms (None: `auto`).
    pub fn given_ms(self) -> Option<f64> {
        match self {
            Readout::Millis(ms) => Some(ms),
            Readout::Auto => None,
        }
    }
}

impl std::str::FromStr for Readout {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        if text.eq_ignore_ascii_case("auto") {
            return Ok(Readout::Auto);
        }
        let v: f64 = text
            .parse()
            .map_err(|e| format!("{text}: {e} (a time in ms, or auto)"))?;
        millis(v)
    }
}

fn millis(v: f64) -> Result<Readout, String> {
    if (0.0..=MAX_READOUT_MS).contains(&v) {
        Ok(Readout::Millis(v))
    } else {
        Err(format!(
            "{v}: must be between 0 and {MAX_READOUT_MS} ms, or auto"
        ))
    }
}

impl std::fmt::Display for Readout {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Readout::Auto => write!(f, "auto"),
            Readout::Millis(ms) => write!(f, "{ms}"),
        }
    }
}

/// When the radial term is self-calibrated (`--calibrate-radial`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RadialSetting {
    /// Only for a calibration without distortion terms (rectified images, or a pinhole
    /// from a datasheet): the residual of a rectification is what one radial term
    /// captures. A calibration that models its lens is trusted: on tum_fr1_rpy's
    /// in-repo JPEG clip (five distortion terms given) the windows agreed on k = -0.014,
    /// which made the map worse (keyframe ATE 1.47 -> 1.64 cm), and the same frames as
    /// PNG gave -0.008.
    Auto,
    /// Always estimated (applied when clear).
    On,
    /// Never.
    Off,
}

impl RadialSetting {
    /// Whether to estimate for `camera`: the first term of its lens model (radial-tangential
    /// k1, equidistant k1, double sphere xi), a fisheye's measured on its own image.
    pub fn applies_to(self, camera: &PinholeRadtan) -> bool {
        match self {
            RadialSetting::Auto => camera.distortion.iter().all(|d| *d == 0.0),
            RadialSetting::On => true,
            RadialSetting::Off => false,
        }
    }
}

impl std::str::FromStr for RadialSetting {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        match text.to_ascii_lowercase().as_str() {
            "auto" => Ok(RadialSetting::Auto),
            "true" => Ok(RadialSetting::On),
            "false" => Ok(RadialSetting::Off),
            _ => Err(format!("{text}: auto, true or false")),
        }
    }
}

impl std::fmt::Display for RadialSetting {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            RadialSetting::Auto => "auto",
            RadialSetting::On => "true",
            RadialSetting::Off => "false",
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_times_and_auto_and_refuses_the_rest() {
        assert_eq!("auto".parse::<Readout>(), Ok(Readout::Auto));
        assert_eq!("AUTO".parse::<Readout>(), Ok(Readout::Auto));
        assert_eq!("25".parse::<Readout>(), Ok(Readout::Millis(25.0)));
        assert!("-1".parse::<Readout>().is_err());
        assert!("101".parse::<Readout>().is_err());
        assert!("fast".parse::<Readout>().is_err());
        assert_eq!(Readout::Millis(12.5).to_string(), "12.5");
    }

    #[test]
    fn auto_estimates_the_radial_term_only_where_the_calibration_models_no_lens() {
        let pinhole =
            PinholeRadtan::new(640, 480, [500.0, 500.0, 320.0, 240.0], [0.0; 5]).expect("camera");
        let lens = PinholeRadtan {
            distortion: [0.26, -0.95, 0.0, 0.0, 1.16],
            ..pinhole
        };
        assert!(RadialSetting::Auto.applies_to(&pinhole));
        assert!(!RadialSetting::Auto.applies_to(&lens));
        assert!(RadialSetting::On.applies_to(&lens));
        assert!(!RadialSetting::Off.applies_to(&pinhole));
        // A fisheye as well: its first term when nominal, trusted when calibrated.
        let nominal_fisheye = pinhole
            .with_lens(egoslam_geometry::LensModel::Equidistant)
            .expect("camera");
        assert!(RadialSetting::Auto.applies_to(&nominal_fisheye));
        let calibrated_fisheye = PinholeRadtan {
            distortion: [0.02, -0.003, 0.0, 0.0, 0.0],
            ..nominal_fisheye
        };
        assert!(!RadialSetting::Auto.applies_to(&calibrated_fisheye));
        for (text, setting) in [
            ("auto", RadialSetting::Auto),
            ("TRUE", RadialSetting::On),
            ("false", RadialSetting::Off),
        ] {
            assert_eq!(text.parse::<RadialSetting>(), Ok(setting));
            assert_eq!(
                setting.to_string().parse::<RadialSetting>(),
                Ok(setting),
                "round trip"
            );
        }
        assert!("yes".parse::<RadialSetting>().is_err());
    }
}
