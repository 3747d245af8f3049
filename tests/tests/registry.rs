//! The registry: every shipped plugin is present under its name and stage, names are unique,
//! and a manual registration works (the path of tests and shared-library plugins).

use capsule_slam_framework::registry::PluginEntry;
use capsule_slam_framework::{Registry, RegistryError, StageKind};
use capsule_slam_tests::stages::{PointFuser, test_registry};

/// Every plugin this build must ship, with its stage.
const EXPECTED: [(&str, StageKind); 4] =
    [("ground-truth", StageKind::Tracker), ("icp-rgb", StageKind::Tracker), ("sensor", StageKind::DepthEstimator), ("surfel-cpu", StageKind::Fuser)];

#[test]
fn every_shipped_plugin_is_registered() {
    capsule_slam_plugins::link();
    let r = Registry::from_inventory().unwrap();
    for (name, kind) in EXPECTED {
        let e = r.get(name).unwrap_or_else(|| panic!("`{name}` is not registered"));
        assert_eq!(e.kind, kind, "{name}");
        assert!(!e.summary.is_empty());
    }
}

#[test]
fn names_are_sorted_and_per_kind() {
    let r = test_registry();
    let all: Vec<_> = r.iter().map(|e| e.name).collect();
    let mut sorted = all.clone();
    sorted.sort();
    assert_eq!(all, sorted);
    assert!(r.names(StageKind::Fuser).contains(&"test-points"));
    assert!(!r.names(StageKind::Fuser).contains(&"sensor"));
}

#[test]
fn duplicate_names_are_an_error() {
    let mut r = test_registry();
    let err = r.register(PluginEntry::fuser::<PointFuser>()).unwrap_err();
    assert!(matches!(err, RegistryError::Duplicate { ref name, .. } if name == "test-points"));
    assert!(err.to_string().contains("unique"));
}

#[test]
fn every_parameter_is_documented_with_a_unit_and_a_valid_default() {
    let r = test_registry();
    for e in r.iter() {
        for p in e.param_docs() {
            assert!(!p.doc.is_empty(), "{}.{} has no doc", e.name, p.name);
            assert!(!p.unit.is_empty(), "{}.{} has no unit", e.name, p.name);
            assert!(p.default.is_some(), "{}.{} has no default", e.name, p.name);
        }
        assert!(e.check(&toml::Table::new()).is_empty(), "{}'s defaults do not validate", e.name);
    }
}
