//! `render` then `detect` through the CLI recovers the rendered pose.

use std::process::Command;

#[test]
fn render_then_detect_round_trip() {
    let exe = env!("CARGO_BIN_EXE_trocar_docking");
    let cam = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config/camera_zedm.yaml");
    let out = std::env::temp_dir().join(format!("vision_cli_{}.png", std::process::id()));
    let r = Command::new(exe)
        .args([
            "render",
            "--family",
            "DICT_ARUCO_ORIGINAL",
            "--id",
            "12",
            "--size",
            "0.06",
        ])
        .args([
            "--distance",
            "0.5",
            "--tilt-deg",
            "20,-10",
            "--noise",
            "2",
            "--json",
            "--camera",
        ])
        .arg(&cam)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    let rendered: serde_json::Value = serde_json::from_slice(&r.stdout).unwrap();
    let d = Command::new(exe)
        .args([
            "detect",
            "--family",
            "DICT_ARUCO_ORIGINAL",
            "--size",
            "0.06",
            "--json",
            "--camera",
        ])
        .arg(&cam)
        .arg("--image")
        .arg(&out)
        .output()
        .unwrap();
    let _ = std::fs::remove_file(&out);
    assert!(d.status.success(), "{}", String::from_utf8_lossy(&d.stderr));
    let found: serde_json::Value = serde_json::from_slice(&d.stdout).unwrap();
    let markers = found["markers"].as_array().unwrap();
    assert_eq!(markers.len(), 1);
    assert_eq!(markers[0]["id"], 12);
    let t = |v: &serde_json::Value| -> Vec<f64> {
        v["translation"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect()
    };
    let (a, b) = (t(&rendered["pose_camera_marker"]), t(&markers[0]["pose_camera_marker"]));
    let err = a.iter().zip(&b).map(|(x, y)| (x - y).powi(2)).sum::<f64>().sqrt();
    assert!(err < 1e-3, "{err} m");
    // A missing image is a clean error, not a panic.
    let bad = Command::new(exe)
        .args(["detect", "--image", "/nonexistent.png", "--camera"])
        .arg(&cam)
        .output()
        .unwrap();
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("cannot read image"));
}

/// Without marker options both commands take the marker the simulator shows and the
/// estimator expects (config/trocar_estimator.yaml `marker:`), so the distance comes out right.
#[test]
fn render_and_detect_default_to_the_shipped_marker() {
    let exe = env!("CARGO_BIN_EXE_trocar_docking");
    let cam = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config/camera_zedm.yaml");
    let out = std::env::temp_dir().join(format!("vision_cli_default_{}.png", std::process::id()));
    let r = Command::new(exe)
        .args(["render", "--distance", "0.3", "--json", "--camera"])
        .arg(&cam)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    let rendered: serde_json::Value = serde_json::from_slice(&r.stdout).unwrap();
    assert_eq!(
        (&rendered["family"], &rendered["id"], &rendered["size_m"]),
        (
            &serde_json::json!("DICT_4X4_50"),
            &serde_json::json!(7),
            &serde_json::json!(0.04)
        )
    );
    let d = Command::new(exe)
        .args(["detect", "--json", "--camera"])
        .arg(&cam)
        .arg("--image")
        .arg(&out)
        .output()
        .unwrap();
    let _ = std::fs::remove_file(&out);
    assert!(d.status.success(), "{}", String::from_utf8_lossy(&d.stderr));
    let found: serde_json::Value = serde_json::from_slice(&d.stdout).unwrap();
    assert_eq!(found["size_m"], 0.04);
    let m = &found["markers"][0];
    assert_eq!(m["id"], 7);
    let z = m["pose_camera_marker"]["translation"][2].as_f64().unwrap();
    assert!((z - 0.3).abs() < 1e-3, "distance {z} m, rendered at 0.3 m");
}
