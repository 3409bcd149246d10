//! The rostests' force bounds are stated in one place, the `.test` file, and the docs quote
//! them: every `tests/ros/*.test` that bounds the metric M and the peak force
//! (`max_metric_m`, `max_force`) has a row in docs/ros.md's "Bounds against measured values"
//! table with exactly those values, and every such row names a file that has them.

use std::collections::BTreeMap;
use std::path::Path;

/// The `value` of every `<param name="NAME" value="..."/>` in a launch file's text.
fn param_values(text: &str, name: &str) -> Vec<f64> {
    let key = format!("name=\"{name}\"");
    text.lines()
        .filter(|l| l.contains("<param") && l.contains(&key))
        .filter_map(|l| l.split("value=\"").nth(1)?.split('"').next()?.parse().ok())
        .collect()
}

/// Each `.test` file's (M bound, peak bound), when it states both (one pair per file).
fn test_bounds(dir: &Path) -> BTreeMap<String, (f64, f64)> {
    let mut out = BTreeMap::new();
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().and_then(|e| e.to_str()) != Some("test") {
            continue;
        }
        let text = std::fs::read_to_string(&path).unwrap();
        let (m, f) = (param_values(&text, "max_metric_m"), param_values(&text, "max_force"));
        let name = path.file_stem().unwrap().to_string_lossy().into_owned();
        assert_eq!(m.len(), f.len(), "{name}: max_metric_m and max_force come in pairs");
        if let (Some(&m0), Some(&f0)) = (m.first(), f.first()) {
            assert!(
                m.iter().all(|&x| x == m0) && f.iter().all(|&x| x == f0),
                "{name}: one M / peak pair per file ({m:?} / {f:?})"
            );
            out.insert(name, (m0, f0));
        }
    }
    out
}

/// The docs table's "M / peak" rows: each test named in the first cell, with the bound cell's
/// leading "A / B N".
fn doc_bounds(text: &str) -> BTreeMap<String, (f64, f64)> {
    let table = text
        .split("### Bounds against measured values")
        .nth(1)
        .expect("docs/ros.md has the section \"Bounds against measured values\"");
    let mut out = BTreeMap::new();
    for line in table.lines().take_while(|l| !l.starts_with("## ")) {
        let cells: Vec<&str> = line.split('|').map(str::trim).collect();
        if cells.len() < 4 || !cells[2].starts_with("M / peak") {
            continue;
        }
        let bound = cells[3].split(';').next().unwrap().trim_end_matches('N').trim();
        let pair: Vec<f64> = bound.split('/').map(|x| x.trim().parse().unwrap()).collect();
        assert_eq!(pair.len(), 2, "{line}: the bound reads \"A / B N\"");
        for name in cells[1].split(',') {
            let name = name.trim().trim_matches('`').to_string();
            assert!(
                out.insert(name.clone(), (pair[0], pair[1])).is_none(),
                "{name}: two rows"
            );
        }
    }
    out
}

#[test]
fn every_rostest_force_bound_is_the_one_the_docs_quote() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let tests = test_bounds(&root.join("tests/ros"));
    let docs = doc_bounds(&std::fs::read_to_string(root.join("docs/ros.md")).unwrap());
    assert!(
        tests.len() >= 10,
        "the docking rostests bound M and the peak: {tests:?}"
    );
    assert_eq!(
        docs, tests,
        "docs/ros.md's M / peak bounds (left) against the .test files' (right)"
    );
}

#[test]
fn the_parsers_read_what_they_are_given() {
    let launch = r#"<test><param name="max_metric_m" value="0.6"/>
        <param name="max_force" value="5.0"/></test>"#;
    assert_eq!(param_values(launch, "max_metric_m"), [0.6]);
    assert_eq!(param_values(launch, "max_force"), [5.0]);
    let doc = "### Bounds against measured values\n| a | b |\n|---|---|\n\
               | `x`, y | M / peak; rate | 0.5 / 2.9 N; 15 Hz | m | w |\n| z | lead | 2.0° | 1 | w |\n## Next\n| q | M / peak | 9 / 9 N |";
    let d = doc_bounds(doc);
    assert_eq!(d.len(), 2);
    assert_eq!(d["x"], (0.5, 2.9));
    assert_eq!(d["y"], (0.5, 2.9));
}
