//! The second chance for a frame whose appearance matches are too few to accept alone
//! (`RelocalizerOptions::tentative`): a weak pose from appearance, accepted only when the
//! matching by projection confirms it. Exact rendered maps, so a pose's error is the
//! relocalizer's own.

mod support;

use egoslam_geometry::StampedPose;
use egoslam_relocalization::descriptors::DescriberOptions;
use egoslam_relocalization::{
    default_vocabulary, Descriptor, OrbDescriber, QueryFeatures, Relocalizer, RelocalizerOptions,
};
use egoslam_synth::{CameraPath, Scene, WalkerOptions};
use support::rendered_map::{described_frame, rendered_map};

/// `descriptor` with `bits` of its 256 bits flipped, chosen by `seed` (a fixed hash, so the
/// test is the same every run).
fn degraded(descriptor: &Descriptor, bits: usize, seed: u64) -> Descriptor {
    let mut out = *descriptor;
    let mut state = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    let mut flipped = 0;
    let mut used = [false; 256];
    while flipped < bits {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        let bit = (state % 256) as usize;
        if !used[bit] {
            used[bit] = true;
            out[bit / 8] ^= 1 << (bit % 8);
            flipped += 1;
        }
    }
    out
}

/// Every query descriptor moved `bits` away from what the map holds: what blur or a
/// change of light does to ORB. At 56 bits appearance matching (64 bits, ratio 0.8) finds
/// too few true matches for most frames; the search by projection (80 bits, near the
/// predicted pixel) still finds many (at 36 bits every frame passed the strict test, at
/// 62 none found even a weak pose).
fn blurred(query: &QueryFeatures, bits: usize) -> QueryFeatures {
    QueryFeatures {
        pixels: query.pixels.clone(),
        descriptors: query
            .descriptors
            .iter()
            .enumerate()
            .map(|(i, d)| degraded(d, bits, i as u64 + 1))
            .collect(),
    }
}

fn error(pose: &StampedPose, truth: &StampedPose) -> (f64, f64) {
    (
        (pose.position - truth.position).norm(),
        pose.rotation.angle_to(&truth.rotation).to_degrees(),
    )
}

#[test]
fn weak_appearance_poses_confirmed_by_projection_are_accepted_and_accurate() {
    let scene = Scene::room(7);
    let poses: Vec<StampedPose> = CameraPath::Walker(WalkerOptions::default()).poses(120, 30.0);
    let mut describer = OrbDescriber::new(DescriberOptions::default()).expect("orb");
    let map = rendered_map(&scene, &poses, 6, &mut describer, |_| {});
    let relocalizer = Relocalizer::new(default_vocabulary().expect("built-in vocabulary"), map);
    let with = RelocalizerOptions::default();
    let without = RelocalizerOptions {
        tentative: None,
        ..with
    };
    let (mut tried, mut strict, mut second_chance) = (0, 0, Vec::new());
    for (i, truth) in poses.iter().enumerate().skip(3).step_by(6) {
        let (query, _, _) = described_frame(&scene, truth, 3000 + i as u64, &mut describer);
        let query = blurred(&query, 56);
        tried += 1;
        let before = relocalizer.relocalize(&query, &without);
        let after = relocalizer.relocalize(&query, &with);
        match (before, after) {
            (Ok(b), Ok(a)) => {
                // A frame the strict test places is placed exactly as before.
                assert_eq!(a, b, "frame {i}: the second chance changed a strict pose");
                strict += 1;
            }
            (Err(_), Ok(a)) => second_chance.push((i, error(&a.pose, truth))),
            (Ok(_), Err(e)) => panic!("frame {i}: lost with the second chance: {e}"),
            (Err(_), Err(_)) => {}
        }
    }
    println!("{tried} frames: {strict} strict, second chance {second_chance:?}");
    // Measured: of 20 frames, 8 strict and 7 more placed by the second chance, each
    // within 4.2 mm and 0.04 deg of the truth (without it those 7 get no pose).
    assert!(
        second_chance.len() >= tried / 4,
        "{} of {tried} frames recovered",
        second_chance.len()
    );
    for (i, (position, angle)) in &second_chance {
        assert!(
            *position < 0.01 && *angle < 0.2,
            "frame {i}: {position} m, {angle} deg off"
        );
    }
}
