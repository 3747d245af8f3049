//! `capsule-slam plugins`.

pub fn run() -> anyhow::Result<()> {
    let registry = crate::registry()?;
    for e in registry.iter() {
        println!("{} ({})", e.name, e.kind.as_str());
        println!("    {}", e.summary);
        if let Some(lib) = e.library() {
            println!("    from the library {}", lib.display());
        }
        let params = e.param_docs();
        if params.is_empty() {
            println!("    no parameters");
        }
        for p in params {
            let default = p.default.map_or_else(|| "-".to_owned(), |v| v.to_string());
            let range = p.range.map(|(lo, hi)| format!(" in [{lo}, {hi}]")).unwrap_or_default();
            println!("    {} = {default}  [{}{range}]", p.name, p.unit);
            println!("        {}", p.doc);
        }
        println!();
    }
    Ok(())
}
