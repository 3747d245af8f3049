//! Typed plugin parameters: serde with `deny_unknown_fields` and defaults, a documented unit and
//! range per field, and validation that reports every problem at once.
//!
//! Declare parameters with [`plugin_params!`](crate::plugin_params):
//! ```
//! capsule_slam_framework::plugin_params! {
//!     /// Parameters of an example plugin.
//!     pub struct ExampleParams {
//!         /// Fusion depth gate along the ray (ElasticFusion: 0.05 m, room scale).
//!         pub depth_gate_m: f64 = 0.003; unit = "m"; range = 0.0..=1.0;
//!         /// Active time window δt.
//!         pub delta_t: u32 = 200; unit = "frames"; range = 1.0..=1.0e6;
//!         /// Free text.
//!         pub label: String = "x".to_string(); unit = "-";
//!     }
//! }
//! ```

use serde::{Serialize, de::DeserializeOwned};

use crate::error::ConfigProblem;

/// Documentation of one parameter.
#[derive(Debug, Clone, PartialEq)]
pub struct ParamDoc {
    /// Key in `[plugins.<name>]`.
    pub name: &'static str,
    /// Unit (`m`, `rad`, `frames`, `-` for dimensionless).
    pub unit: &'static str,
    /// Doc comment: meaning and source.
    pub doc: String,
    /// Default value as TOML.
    pub default: Option<toml::Value>,
    /// Valid closed range, for numeric parameters.
    pub range: Option<(f64, f64)>,
}

/// A plugin's parameter set.
pub trait PluginParams: Serialize + DeserializeOwned + Default + Clone + std::fmt::Debug + Send + 'static {
    /// One entry per field, in declaration order.
    fn docs() -> Vec<ParamDoc>;

    /// Every out-of-range value, as `(field, message)`.
    fn range_problems(&self) -> Vec<(&'static str, String)>;

    /// Plugin-specific cross-field checks beyond ranges, as `(field, message)`.
    fn extra_problems(&self) -> Vec<(&'static str, String)> {
        Vec::new()
    }
}

/// Whether a value lies in the closed range (NaN never does).
pub fn in_range(value: f64, lo: f64, hi: f64) -> bool {
    value >= lo && value <= hi
}

/// Parses and validates a `[plugins.<plugin>]` table, reporting every unknown key, type error
/// and out-of-range value with its fix.
pub fn parse_params<P: PluginParams>(plugin: &str, table: &toml::Table) -> Result<P, Vec<ConfigProblem>> {
    let docs = P::docs();
    let known: Vec<&str> = docs.iter().map(|d| d.name).collect();
    let mut problems: Vec<ConfigProblem> = table
        .keys()
        .filter(|k| !known.contains(&k.as_str()))
        .map(|k| {
            let fix =
                if known.is_empty() { format!("remove it: `{plugin}` has no parameters") } else { format!("remove it or use one of: {}", known.join(", ")) };
            ConfigProblem::new(format!("plugins.{plugin}.{k}"), "unknown key", fix)
        })
        .collect();
    if !problems.is_empty() {
        return Err(problems);
    }
    let params: P = match toml::Value::Table(table.clone()).try_into() {
        Ok(p) => p,
        Err(e) => {
            let msg = e.to_string().trim().replace('\n', " ");
            return Err(vec![ConfigProblem::new(format!("plugins.{plugin}"), msg, "see `capsule-slam plugins` for each key's type and default")]);
        }
    };
    for (field, msg) in params.range_problems().into_iter().chain(params.extra_problems()) {
        let doc = docs.iter().find(|d| d.name == field);
        let fix = match doc.and_then(|d| d.range.map(|r| (r, d.unit))) {
            Some(((lo, hi), unit)) => format!("use a value in [{lo}, {hi}] {unit}"),
            None => "see `capsule-slam plugins`".to_owned(),
        };
        problems.push(ConfigProblem::new(format!("plugins.{plugin}.{field}"), msg, fix));
    }
    if problems.is_empty() { Ok(params) } else { Err(problems) }
}

/// Declares a plugin's parameter struct: serde (`deny_unknown_fields`, `default`), `Default`
/// from the declared values, and [`PluginParams`] with docs, units and range checks.
/// Numeric fields may carry `range = lo..=hi` (floats); the crate using it depends on serde.
#[macro_export]
macro_rules! plugin_params {
    (
        $(#[$smeta:meta])*
        pub struct $name:ident {
            $(
                $(#[doc = $doc:literal])*
                pub $field:ident : $ty:ty = $default:expr ; unit = $unit:literal $(; range = $lo:literal ..= $hi:literal)? ;
            )*
        }
    ) => {
        $(#[$smeta])*
        #[derive(Debug, Clone, PartialEq, ::serde::Serialize, ::serde::Deserialize)]
        #[serde(deny_unknown_fields, default)]
        pub struct $name {
            $( $(#[doc = $doc])* pub $field: $ty, )*
        }

        impl Default for $name {
            fn default() -> Self {
                Self { $( $field: $default, )* }
            }
        }

        impl $crate::params::PluginParams for $name {
            #[allow(unused_variables)]
            fn docs() -> Vec<$crate::params::ParamDoc> {
                let d = Self::default();
                vec![ $(
                    $crate::params::ParamDoc {
                        name: stringify!($field),
                        unit: $unit,
                        doc: [$($doc),*].iter().map(|l: &&str| l.trim()).collect::<Vec<_>>().join(" "),
                        default: $crate::toml::Value::try_from(&d.$field).ok(),
                        range: $crate::plugin_params!(@range $($lo, $hi)?),
                    },
                )* ]
            }

            #[allow(unused_mut)]
            fn range_problems(&self) -> Vec<(&'static str, String)> {
                let mut out = Vec::new();
                $( $(
                    #[allow(clippy::cast_lossless, clippy::unnecessary_cast)]
                    let v = self.$field as f64;
                    if !$crate::params::in_range(v, $lo as f64, $hi as f64) {
                        out.push((stringify!($field), format!("value {} is out of range", v)));
                    }
                )? )*
                out
            }
        }
    };
    (@range $lo:literal, $hi:literal) => { Some(($lo as f64, $hi as f64)) };
    (@range) => { None };
}

#[cfg(test)]
mod tests {
    use super::*;

    crate::plugin_params! {
        /// Test parameters.
        pub struct TestParams {
            /// A gate, in metres.
            pub gate_m: f64 = 0.003; unit = "m"; range = 0.0..=1.0;
            /// A count.
            pub delta_t: u32 = 200; unit = "frames"; range = 1.0..=100000.0;
            /// A name.
            pub mode: String = "a".to_string(); unit = "-";
        }
    }

    fn table(s: &str) -> toml::Table {
        toml::from_str(s).unwrap()
    }

    #[test]
    fn defaults_and_docs() {
        let docs = TestParams::docs();
        assert_eq!(docs.len(), 3);
        assert_eq!(docs[0].name, "gate_m");
        assert_eq!(docs[0].unit, "m");
        assert_eq!(docs[0].doc, "A gate, in metres.");
        assert_eq!(docs[0].default, Some(toml::Value::Float(0.003)));
        assert_eq!(docs[1].range, Some((1.0, 100000.0)));
        assert_eq!(docs[2].range, None);
        let p: TestParams = parse_params("t", &toml::Table::new()).unwrap();
        assert_eq!(p, TestParams::default());
    }

    #[test]
    fn every_unknown_key_is_reported() {
        let err = parse_params::<TestParams>("t", &table("foo = 1\nbar = 2")).unwrap_err();
        let keys: Vec<_> = err.iter().map(|p| p.key.as_str()).collect();
        assert_eq!(keys, vec!["plugins.t.bar", "plugins.t.foo"]);
        assert!(err[0].fix.contains("gate_m, delta_t, mode"));
    }

    #[test]
    fn every_out_of_range_value_is_reported() {
        let err = parse_params::<TestParams>("t", &table("gate_m = -1.0\ndelta_t = 0")).unwrap_err();
        assert_eq!(err.len(), 2);
        assert_eq!(err[0].key, "plugins.t.gate_m");
        assert!(err[0].fix.contains("[0, 1] m"), "{}", err[0].fix);
    }

    #[test]
    fn nan_is_out_of_range() {
        let err = parse_params::<TestParams>("t", &table("gate_m = nan")).unwrap_err();
        assert_eq!(err[0].key, "plugins.t.gate_m");
    }

    #[test]
    fn type_errors_are_reported() {
        let err = parse_params::<TestParams>("t", &table("gate_m = \"wide\"")).unwrap_err();
        assert_eq!(err[0].key, "plugins.t");
        assert!(err[0].message.contains("gate_m") || err[0].message.contains("float"), "{}", err[0].message);
    }

    #[test]
    fn integers_are_accepted_for_floats() {
        let p: TestParams = parse_params("t", &table("gate_m = 1")).unwrap();
        assert_eq!(p.gate_m, 1.0);
    }
}
