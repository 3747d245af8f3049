//! `--set KEY=VALUE` overrides: `KEY` is a dotted path into the config, `VALUE` a TOML value;
//! a bare word is taken as a string (`--set pipeline.depth=sensor`).

use crate::error::ConfigProblem;

/// Parses the value of an override: TOML if it parses, else a bare string.
pub fn parse_value(text: &str) -> toml::Value {
    let text = text.trim();
    match format!("v = {text}").parse::<toml::Table>() {
        Ok(mut t) => t.remove("v").unwrap_or_else(|| toml::Value::String(text.to_owned())),
        Err(_) => toml::Value::String(text.to_owned()),
    }
}

/// Applies one `KEY=VALUE` assignment to a config table, creating tables along the path.
pub fn apply(table: &mut toml::Table, assignment: &str) -> Result<(), ConfigProblem> {
    let Some((key, value)) = assignment.split_once('=') else {
        return Err(ConfigProblem::new(assignment, "an override needs the form KEY=VALUE", "write e.g. --set pipeline.depth=sensor"));
    };
    let parts: Vec<&str> = key.trim().split('.').map(str::trim).collect();
    if parts.iter().any(|p| p.is_empty()) {
        return Err(ConfigProblem::new(key, "empty key segment", "write a dotted path such as plugins.surfel-cpu.delta_t"));
    }
    let (last, path) = parts.split_last().ok_or_else(|| ConfigProblem::new(key, "empty key", "write a dotted path"))?;
    let mut cur = table;
    for (i, p) in path.iter().enumerate() {
        let entry = cur.entry((*p).to_owned()).or_insert_with(|| toml::Value::Table(toml::Table::new()));
        cur = match entry {
            toml::Value::Table(t) => t,
            _ => {
                let at = parts[..=i].join(".");
                return Err(ConfigProblem::new(key, format!("`{at}` is a value, not a table"), format!("override `{at}` itself")));
            }
        };
    }
    cur.insert((*last).to_owned(), parse_value(value));
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_parse_as_toml_or_string() {
        assert_eq!(parse_value("100"), toml::Value::Integer(100));
        assert_eq!(parse_value("0.5"), toml::Value::Float(0.5));
        assert_eq!(parse_value("true"), toml::Value::Boolean(true));
        assert_eq!(parse_value("sensor"), toml::Value::String("sensor".into()));
        assert_eq!(parse_value("icp-rgb"), toml::Value::String("icp-rgb".into()));
        assert_eq!(parse_value("\"quoted\""), toml::Value::String("quoted".into()));
        let arr = parse_value(r#"["reflection","vignetting"]"#);
        assert_eq!(arr.as_array().map(|a| a.len()), Some(2));
        assert_eq!(parse_value("[]").as_array().map(|a| a.len()), Some(0));
    }

    #[test]
    fn apply_creates_tables() {
        let mut t = toml::Table::new();
        apply(&mut t, "plugins.surfel-cpu.delta_t=100").unwrap();
        assert_eq!(t["plugins"]["surfel-cpu"]["delta_t"].as_integer(), Some(100));
        apply(&mut t, "plugins.surfel-cpu.delta_t=50").unwrap();
        assert_eq!(t["plugins"]["surfel-cpu"]["delta_t"].as_integer(), Some(50));
    }

    #[test]
    fn bad_assignments_are_problems() {
        let mut t = toml::Table::new();
        assert!(apply(&mut t, "pipeline.depth").is_err());
        assert!(apply(&mut t, "a..b=1").is_err());
        apply(&mut t, "a=1").unwrap();
        let p = apply(&mut t, "a.b=1").unwrap_err();
        assert!(p.message.contains("not a table"));
    }
}
