//! The shipped iceoryx2 configuration is iceoryx2's defaults, complete and loadable.

use iceoryx2::prelude::*;

#[test]
fn shipped_config_is_the_default_and_loads() {
    let path = egoslam_bus::config_path();
    let default = toml::to_string(&Config::default()).expect("serialises");
    if std::env::var_os("EGOSLAM_WRITE_ICEORYX2_CONFIG").is_some() {
        std::fs::write(&path, format!("# iceoryx2 0.10 defaults (egoslam loads this as the global config), written by\n# services/bus/tests/config_file.rs with EGOSLAM_WRITE_ICEORYX2_CONFIG=1\n{default}")).expect("write");
        // A run that wrote the reference cannot also check it against itself.
        panic!(
            "{} rewritten; run again without EGOSLAM_WRITE_ICEORYX2_CONFIG to check it",
            path.display()
        );
    }
    let text = std::fs::read_to_string(&path).expect("config/iceoryx2.toml is shipped");
    let parsed: Config = toml::from_str(&text).expect("parses");
    assert_eq!(
        toml::to_string(&parsed).expect("serialises"),
        default,
        "config/iceoryx2.toml differs from iceoryx2's defaults"
    );
    let file = FilePath::new(path.to_str().expect("utf-8").as_bytes()).expect("path");
    assert!(Config::from_file(&file).is_ok());
}
