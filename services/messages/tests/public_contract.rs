//! The client contract changes only compatibly: every message field and enum value of
//! package `egoslam.v1` recorded in `proto/egoslam/v1/contract.txt` is still there with the
//! same number, name, type and label. Adding is allowed (and must be recorded, so that it
//! is kept from then on); removing, renumbering, renaming or retyping fails. The internal
//! package is free to change.

use prost::Message;
use prost_types::field_descriptor_proto::{Label, Type};
use prost_types::{DescriptorProto, EnumDescriptorProto, FileDescriptorSet};
use std::collections::BTreeSet;
use std::path::Path;

const PUBLIC_PACKAGE: &str = "egoslam.v1";

fn enum_lines(scope: &str, e: &EnumDescriptorProto, out: &mut BTreeSet<String>) {
    let name = format!("{scope}.{}", e.name());
    for v in &e.value {
        out.insert(format!("enum {name} {} {}", v.number(), v.name()));
    }
}

fn message_lines(scope: &str, m: &DescriptorProto, out: &mut BTreeSet<String>) {
    let name = format!("{scope}.{}", m.name());
    for f in &m.field {
        let label = match f.label() {
            Label::Repeated => "repeated",
            Label::Optional if f.proto3_optional() => "optional",
            Label::Optional => "singular",
            Label::Required => "required",
        };
        let kind = match f.r#type() {
            Type::Message | Type::Enum => f.type_name().to_string(),
            other => other
                .as_str_name()
                .trim_start_matches("TYPE_")
                .to_lowercase(),
        };
        out.insert(format!(
            "field {name} {} {} {kind} {label}",
            f.number(),
            f.name()
        ));
    }
    for nested in &m.nested_type {
        message_lines(&name, nested, out);
    }
    for e in &m.enum_type {
        enum_lines(&name, e, out);
    }
}

/// One line per field and enum value of the public package, as built now.
fn public_contract() -> BTreeSet<String> {
    let set = FileDescriptorSet::decode(egoslam_messages::DESCRIPTORS).expect("descriptor set");
    let mut out = BTreeSet::new();
    for file in set.file.iter().filter(|f| f.package() == PUBLIC_PACKAGE) {
        let scope = format!(".{PUBLIC_PACKAGE}");
        for m in &file.message_type {
            message_lines(&scope, m, &mut out);
        }
        for e in &file.enum_type {
            enum_lines(&scope, e, &mut out);
        }
    }
    out
}

#[test]
fn the_public_package_changes_only_compatibly() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../proto/egoslam/v1/contract.txt");
    let recorded: BTreeSet<String> = std::fs::read_to_string(&path)
        .expect("proto/egoslam/v1/contract.txt")
        .lines()
        .filter(|l| !l.is_empty() && !l.starts_with('#'))
        .map(str::to_string)
        .collect();
    let now = public_contract();
    let broken: Vec<&String> = recorded.difference(&now).collect();
    assert!(
        broken.is_empty(),
        "the client contract (egoslam.v1) lost or changed, which breaks clients: {broken:#?}"
    );
    let added: Vec<&String> = now.difference(&recorded).collect();
    assert!(
        added.is_empty(),
        "new in egoslam.v1, not yet recorded: append these lines to \
         proto/egoslam/v1/contract.txt: {added:#?}"
    );
}

#[test]
fn the_internal_package_holds_no_public_name() {
    // A message moved to the internal package under a public name would make a client's
    // decoder and egoslam disagree silently.
    let set = FileDescriptorSet::decode(egoslam_messages::DESCRIPTORS).expect("descriptor set");
    let names = |package: &str| -> BTreeSet<String> {
        set.file
            .iter()
            .filter(|f| f.package() == package)
            .flat_map(|f| {
                let messages = f.message_type.iter().map(|m| m.name().to_string());
                messages.chain(f.enum_type.iter().map(|e| e.name().to_string()))
            })
            .collect()
    };
    let public = names(PUBLIC_PACKAGE);
    let internal = names("egoslam.internal.v1");
    assert!(public.contains("Pose") && internal.contains("WindowSolution"));
    assert!(
        public.is_disjoint(&internal),
        "{:?}",
        public.intersection(&internal)
    );
}
