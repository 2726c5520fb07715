use egoslam_relocalization::descriptors::*;
use std::time::Instant;
fn main() {
    let img = opencv::imgcodecs::imread("tests/data/tum_fr1_rpy_120/rgb/1305031229.528748.jpg", opencv::imgcodecs::IMREAD_GRAYSCALE).unwrap();
    let mut d = OrbDescriber::new(DescriberOptions::default()).unwrap();
    for _ in 0..3 {
        let t = Instant::now();
        let corners = detect_corners(&img, &QueryCornerOptions::default()).unwrap();
        let t1 = t.elapsed().as_secs_f64() * 1e3;
        let desc = d.describe(&img, &corners).unwrap();
        let t2 = t.elapsed().as_secs_f64() * 1e3;
        println!("gftt {t1:.1} ms, describe {:.1} ms ({} described)", t2 - t1, desc.iter().flatten().count());
    }
}
