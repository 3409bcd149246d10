//! RViz markers of a docking scene (`/docking/markers`): the insertion axis and the port of
//! the trocar, the goal, the endoscope tip and its optical axis, the external force arrow and
//! the admittance reference r; after docking, the fulcrum (the remote centre of motion) and
//! the cone about the docking axis the shaft must stay in. Only message assembly; the
//! geometry comes from the controller.

use nalgebra::{Isometry3, Point3, Vector3};

use super::convert::{header, point_msg, pose_msg};
use super::msgs::{std_msgs, visualization_msgs};
use crate::control::PivotReport;
use crate::vision::markerless::TrocarModel;

/// What to draw, all in the base frame.
#[derive(Debug, Clone)]
pub struct Scene {
    /// The trocar pose (origin at the port, z along the insertion direction), if known.
    pub trocar: Option<Isometry3<f64>>,
    /// The docking goal, if known.
    pub goal: Option<Point3<f64>>,
    /// The endoscope tip pose (z = optical axis), if known.
    pub tip: Option<Isometry3<f64>>,
    /// External force at the tip, N.
    pub f_ext: Vector3<f64>,
    /// The admittance reference r, if any.
    pub reference: Option<Point3<f64>>,
    /// The pivot while the port is held as the remote centre of motion (DONE, RETRACT).
    pub pivot: Option<PivotReport>,
}

/// Marker sizes.
#[derive(Debug, Clone, Copy, serde::Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct MarkerStyle {
    /// Length of the drawn insertion axis (beyond and before the port), m.
    pub axis_length_m: f64,
    /// Length of the drawn optical axis, m.
    pub optical_axis_length_m: f64,
    /// Force arrow length per newton, m/N.
    pub force_scale_m_per_n: f64,
    /// Longest force arrow, m (larger forces are drawn this long; the label gives the value).
    pub force_max_length_m: f64,
    /// Diameter of the spheres, m.
    pub sphere_diameter_m: f64,
    /// The trocar drawn (head and cannula): the shipped `config/trocar_model.yaml`.
    #[serde(skip, default = "TrocarModel::shipped")]
    pub trocar: TrocarModel,
    /// Length of each nappe of the drawn cone of the shaft, from the fulcrum, m.
    pub cone_length_m: f64,
}

crate::shipped_defaults!(
    MarkerStyle,
    crate::config::DOCKING_CONTROLLER_NODE,
    ["markers"],
    deserialize_only
);

/// Marker ids (one marker each, replaced in place).
#[derive(Debug, Clone, Copy)]
enum Id {
    Axis = 0,
    Port = 1,
    Goal = 2,
    Tip = 3,
    OpticalAxis = 4,
    Force = 5,
    Reference = 6,
    TrocarBody = 7,
    ForceLabel = 8,
    Fulcrum = 9,
    Cone = 10,
    TipPath = 11,
    TrocarHead = 12,
}

/// Points on each rim of the drawn cone; every `CONE_RIM / CONE_GENERATORS`-th one is
/// joined to the apex.
const CONE_RIM: usize = 24;
const CONE_GENERATORS: usize = 8;

const NS: &str = "docking";
/// The namespace of the fulcrum and the cone (RViz shows or hides them together).
const PIVOT_NS: &str = "pivot";
/// The namespace of the dry run's tip path.
const DRY_RUN_NS: &str = "dry_run";

fn color(r: f32, g: f32, b: f32) -> std_msgs::ColorRGBA {
    std_msgs::ColorRGBA { r, g, b, a: 1.0 }
}

fn base(stamp: rosrust::Time, frame: &str, id: Id, kind: i32) -> visualization_msgs::Marker {
    let mut m = visualization_msgs::Marker {
        header: header(stamp, frame),
        ns: NS.into(),
        id: id as i32,
        type_: kind,
        action: visualization_msgs::Marker::ADD as i32,
        pose: pose_msg(&Isometry3::identity()),
        ..Default::default()
    };
    m.scale.x = 1.0;
    m.scale.y = 1.0;
    m.scale.z = 1.0;
    m
}

fn arrow(
    stamp: rosrust::Time,
    frame: &str,
    id: Id,
    from: Point3<f64>,
    to: Point3<f64>,
    c: std_msgs::ColorRGBA,
) -> visualization_msgs::Marker {
    let mut m = base(stamp, frame, id, visualization_msgs::Marker::ARROW as i32);
    m.points = vec![point_msg(&from), point_msg(&to)];
    m.scale.x = 0.004;
    m.scale.y = 0.008;
    m.scale.z = 0.012;
    m.color = c;
    m
}

fn sphere(
    stamp: rosrust::Time,
    frame: &str,
    id: Id,
    at: Point3<f64>,
    d: f64,
    c: std_msgs::ColorRGBA,
) -> visualization_msgs::Marker {
    let mut m = base(stamp, frame, id, visualization_msgs::Marker::SPHERE as i32);
    m.pose = pose_msg(&Isometry3::translation(at.x, at.y, at.z));
    m.scale.x = d;
    m.scale.y = d;
    m.scale.z = d;
    m.color = c;
    m
}

fn delete(stamp: rosrust::Time, frame: &str, id: Id) -> visualization_msgs::Marker {
    let mut m = base(stamp, frame, id, visualization_msgs::Marker::SPHERE as i32);
    m.action = visualization_msgs::Marker::DELETE as i32;
    m
}

/// The MarkerArray of `scene` in `frame`; what is unknown is deleted, so RViz shows no stale
/// geometry.
pub fn docking_markers(
    stamp: rosrust::Time,
    frame: &str,
    scene: &Scene,
    style: &MarkerStyle,
) -> visualization_msgs::MarkerArray {
    let mut markers = Vec::with_capacity(12);
    match &scene.trocar {
        Some(t) => trocar_markers(&mut markers, stamp, frame, t, style),
        None => {
            for id in [Id::Axis, Id::Port, Id::TrocarBody, Id::TrocarHead] {
                markers.push(delete(stamp, frame, id));
            }
        }
    }
    match scene.goal {
        Some(g) => markers.push(sphere(
            stamp,
            frame,
            Id::Goal,
            g,
            style.sphere_diameter_m,
            color(0.1, 1.0, 0.2),
        )),
        None => markers.push(delete(stamp, frame, Id::Goal)),
    }
    match &scene.tip {
        Some(tip) => tip_markers(&mut markers, stamp, frame, tip, &scene.f_ext, style),
        None => {
            for id in [Id::Tip, Id::OpticalAxis, Id::Force, Id::ForceLabel] {
                markers.push(delete(stamp, frame, id));
            }
        }
    }
    match scene.reference {
        Some(r) => markers.push(sphere(
            stamp,
            frame,
            Id::Reference,
            r,
            style.sphere_diameter_m * 0.8,
            color(0.9, 0.2, 0.9),
        )),
        None => markers.push(delete(stamp, frame, Id::Reference)),
    }
    let mut pivot = match &scene.pivot {
        Some(p) => [
            sphere(
                stamp,
                frame,
                Id::Fulcrum,
                p.fulcrum,
                style.sphere_diameter_m * 1.2,
                color(1.0, 0.2, 0.6),
            ),
            cone(stamp, frame, p, style.cone_length_m),
        ],
        None => [delete(stamp, frame, Id::Fulcrum), delete(stamp, frame, Id::Cone)],
    };
    for m in &mut pivot {
        m.ns = PIVOT_NS.into();
    }
    markers.extend(pivot);
    visualization_msgs::MarkerArray { markers }
}

/// The cone the shaft stays in: a line list of both nappes about the cone axis through the
/// fulcrum (the shaft is a line through it), each `length` long along its generators, with
/// their rims.
fn cone(stamp: rosrust::Time, frame: &str, p: &PivotReport, length: f64) -> visualization_msgs::Marker {
    let mut m = base(stamp, frame, Id::Cone, visualization_msgs::Marker::LINE_LIST as i32);
    m.scale.x = 0.001;
    m.color = std_msgs::ColorRGBA {
        r: 1.0,
        g: 0.2,
        b: 0.6,
        a: 0.5,
    };
    let axis = p.cone_axis.try_normalize(1e-9).unwrap_or_else(Vector3::z);
    let u = axis
        .cross(&Vector3::x())
        .try_normalize(1e-3)
        .unwrap_or_else(|| axis.cross(&Vector3::y()).normalize());
    let v = axis.cross(&u);
    let (sin, cos) = p.cone_half_angle.sin_cos();
    let rim = |side: f64, k: usize| {
        let phi = std::f64::consts::TAU * k as f64 / CONE_RIM as f64;
        let dir = axis * cos + (u * phi.cos() + v * phi.sin()) * sin;
        point_msg(&(p.fulcrum + dir * side * length))
    };
    let apex = point_msg(&p.fulcrum);
    m.points = Vec::with_capacity(4 * (CONE_RIM + CONE_GENERATORS));
    for side in [1.0, -1.0] {
        for k in 0..CONE_RIM {
            m.points.push(rim(side, k));
            m.points.push(rim(side, k + 1));
            if k % (CONE_RIM / CONE_GENERATORS) == 0 {
                m.points.push(apex.clone());
                m.points.push(rim(side, k));
            }
        }
    }
    m
}

/// The insertion axis, the port and the cannula of the trocar at `t`.
fn trocar_markers(
    markers: &mut Vec<visualization_msgs::Marker>,
    stamp: rosrust::Time,
    frame: &str,
    t: &Isometry3<f64>,
    style: &MarkerStyle,
) {
    let port = Point3::from(t.translation.vector);
    let dir = t.rotation * Vector3::z();
    let from = port - dir * style.axis_length_m;
    let to = port + dir * style.axis_length_m;
    markers.push(arrow(stamp, frame, Id::Axis, from, to, color(0.1, 0.8, 1.0)));
    markers.push(sphere(
        stamp,
        frame,
        Id::Port,
        port,
        style.sphere_diameter_m * 1.5,
        color(1.0, 0.6, 0.0),
    ));
    let [head, cannula] = trocar_solids(stamp, frame, t, &style.trocar, ESTIMATE_COLOR);
    markers.push(with_id(head, NS, Id::TrocarHead as i32));
    markers.push(with_id(cannula, NS, Id::TrocarBody as i32));
}

/// The estimate's trocar: translucent blue-grey.
const ESTIMATE_COLOR: std_msgs::ColorRGBA = std_msgs::ColorRGBA {
    r: 0.5,
    g: 0.55,
    b: 1.0,
    a: 0.6,
};

/// The true trocar (simulation): translucent green.
const TRUTH_COLOR: std_msgs::ColorRGBA = std_msgs::ColorRGBA {
    r: 0.2,
    g: 0.9,
    b: 0.3,
    a: 0.45,
};

/// The abdominal wall (simulation): translucent skin.
const WALL_COLOR: std_msgs::ColorRGBA = std_msgs::ColorRGBA {
    r: 0.95,
    g: 0.7,
    b: 0.6,
    a: 0.35,
};

/// The drawn wall: a disc this wide and this thick about the fulcrum, m.
const WALL_DIAMETER_M: f64 = 0.14;
const WALL_THICKNESS_M: f64 = 0.004;

/// The namespace of the simulator's truth.
const TRUTH_NS: &str = "truth";

fn with_id(mut m: visualization_msgs::Marker, ns: &str, id: i32) -> visualization_msgs::Marker {
    m.ns = ns.into();
    m.id = id;
    m
}

/// A cylinder of `radius` along the z axis of `t` from `z0` to `z1` (frame of `t`).
fn cylinder(
    stamp: rosrust::Time,
    frame: &str,
    t: &Isometry3<f64>,
    radius: f64,
    (z0, z1): (f64, f64),
    c: std_msgs::ColorRGBA,
) -> visualization_msgs::Marker {
    let mut m = base(
        stamp,
        frame,
        Id::TrocarBody,
        visualization_msgs::Marker::CYLINDER as i32,
    );
    let centre = t * Point3::new(0.0, 0.0, 0.5 * (z0 + z1));
    m.pose = pose_msg(&Isometry3::from_parts(centre.coords.into(), t.rotation));
    m.scale.x = 2.0 * radius;
    m.scale.y = 2.0 * radius;
    m.scale.z = z1 - z0;
    m.color = c;
    m
}

/// The trocar `model` at port pose `t` (origin at the opening on the head's top face, z into
/// the body): its head from the face down, and its cannula below the head.
fn trocar_solids(
    stamp: rosrust::Time,
    frame: &str,
    t: &Isometry3<f64>,
    model: &TrocarModel,
    c: std_msgs::ColorRGBA,
) -> [visualization_msgs::Marker; 2] {
    let h = model.head.height;
    [
        cylinder(stamp, frame, t, model.head.radius, (0.0, h), c.clone()),
        cylinder(stamp, frame, t, model.cannula.radius, (h, h + model.cannula.length), c),
    ]
}

/// The simulator's truth in `frame` (namespace `truth`): the true trocar (`trocar`, the
/// `model`'s head and cannula) and the abdominal wall holding it, a disc through `fulcrum`
/// (where the wall holds the trocar) across the true axis; beside the estimate's trocar, it
/// shows the error a calibration leaves.
pub fn truth_markers(
    stamp: rosrust::Time,
    frame: &str,
    trocar: &Isometry3<f64>,
    fulcrum: &Point3<f64>,
    model: &TrocarModel,
) -> visualization_msgs::MarkerArray {
    let [head, cannula] = trocar_solids(stamp, frame, trocar, model, TRUTH_COLOR);
    let across = Isometry3::from_parts(fulcrum.coords.into(), trocar.rotation);
    let half = 0.5 * WALL_THICKNESS_M;
    let wall = cylinder(stamp, frame, &across, 0.5 * WALL_DIAMETER_M, (-half, half), WALL_COLOR);
    visualization_msgs::MarkerArray {
        markers: vec![
            with_id(head, TRUTH_NS, 0),
            with_id(cannula, TRUTH_NS, 1),
            with_id(wall, TRUTH_NS, 2),
        ],
    }
}

/// The dry run's tip path: a line through `points` (base frame), in its own namespace
/// `dry_run`; fewer than two points draw nothing (the marker is deleted).
pub fn tip_path<'a>(
    stamp: rosrust::Time,
    frame: &str,
    points: impl Iterator<Item = &'a Point3<f64>>,
    style: &MarkerStyle,
) -> visualization_msgs::Marker {
    let mut m = base(stamp, frame, Id::TipPath, visualization_msgs::Marker::LINE_STRIP as i32);
    m.ns = DRY_RUN_NS.into();
    m.points = points.map(point_msg).collect();
    if m.points.len() < 2 {
        m.points.clear();
        m.action = visualization_msgs::Marker::DELETE as i32;
    }
    m.scale.x = style.sphere_diameter_m / 6.0;
    m.color = color(0.2, 0.8, 1.0);
    m
}

/// The tip, its optical axis, and the force arrow with its label (deleted when the force
/// is too small to draw).
fn tip_markers(
    markers: &mut Vec<visualization_msgs::Marker>,
    stamp: rosrust::Time,
    frame: &str,
    tip: &Isometry3<f64>,
    f: &Vector3<f64>,
    style: &MarkerStyle,
) {
    let at = Point3::from(tip.translation.vector);
    markers.push(sphere(
        stamp,
        frame,
        Id::Tip,
        at,
        style.sphere_diameter_m,
        color(1.0, 1.0, 1.0),
    ));
    let axis = tip.rotation * Vector3::z() * style.optical_axis_length_m;
    markers.push(arrow(
        stamp,
        frame,
        Id::OpticalAxis,
        at,
        at + axis,
        color(1.0, 1.0, 0.2),
    ));
    let len = (f.norm() * style.force_scale_m_per_n).min(style.force_max_length_m);
    if !(f.iter().all(|x| x.is_finite()) && len > 1e-3) {
        markers.push(delete(stamp, frame, Id::Force));
        markers.push(delete(stamp, frame, Id::ForceLabel));
        return;
    }
    let to = at + f.normalize() * len;
    let mut a = arrow(stamp, frame, Id::Force, at, to, color(1.0, 0.1, 0.1));
    // Thicker than the geometry arrows: the force is what the surgeon watches.
    (a.scale.x, a.scale.y, a.scale.z) = (0.007, 0.014, 0.02);
    markers.push(a);
    let mut label = base(
        stamp,
        frame,
        Id::ForceLabel,
        visualization_msgs::Marker::TEXT_VIEW_FACING as i32,
    );
    label.pose = pose_msg(&Isometry3::translation(to.x, to.y, to.z + 0.015));
    label.scale.z = 0.015;
    label.color = color(1.0, 0.3, 0.3);
    label.text = format!("|f_ext| {:.2} N", f.norm());
    markers.push(label);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn full_scene_has_nine_markers_and_force_arrow_follows_the_force() {
        let scene = Scene {
            trocar: Some(Isometry3::translation(0.5, 0.0, 0.3)),
            goal: Some(Point3::new(0.5, 0.0, 0.33)),
            tip: Some(Isometry3::translation(0.5, 0.0, 0.2)),
            f_ext: Vector3::new(0.0, 0.0, -0.5),
            reference: Some(Point3::new(0.5, 0.0, 0.21)),
            pivot: None,
        };
        let style = MarkerStyle::default();
        let a = docking_markers(rosrust::Time::new(), "lbr_link_0", &scene, &style);
        assert_eq!(a.markers.len(), 12);
        let del = visualization_msgs::Marker::DELETE as i32;
        assert!(a
            .markers
            .iter()
            .filter(|m| m.id == Id::Fulcrum as i32 || m.id == Id::Cone as i32)
            .all(|m| m.action == del));
        let add = visualization_msgs::Marker::ADD as i32;
        assert!(a
            .markers
            .iter()
            .filter(|m| m.id <= Id::ForceLabel as i32)
            .all(|m| m.action == add && m.header.frame_id == "lbr_link_0"));
        let force = a.markers.iter().find(|m| m.id == Id::Force as i32).unwrap();
        assert!((force.points[1].z - (0.2 - 0.5 * style.force_scale_m_per_n)).abs() < 1e-12);
        let label = a.markers.iter().find(|m| m.id == Id::ForceLabel as i32).unwrap();
        assert_eq!(label.text, "|f_ext| 0.50 N");
        // A large force is drawn at the longest length, pointing the same way.
        let big = Scene {
            f_ext: Vector3::new(0.0, 0.0, -50.0),
            ..scene.clone()
        };
        let a = docking_markers(rosrust::Time::new(), "lbr_link_0", &big, &style);
        let force = a.markers.iter().find(|m| m.id == Id::Force as i32).unwrap();
        assert!((force.points[1].z - (0.2 - style.force_max_length_m)).abs() < 1e-12);
        let axis = a.markers.iter().find(|m| m.id == Id::Axis as i32).unwrap();
        assert!((axis.points[1].z - (0.3 + style.axis_length_m)).abs() < 1e-12);
    }

    /// The cylinder's two end points along its own z, base frame.
    fn ends(m: &visualization_msgs::Marker) -> (Point3<f64>, Point3<f64>) {
        let p = &m.pose;
        let q = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
            p.orientation.w,
            p.orientation.x,
            p.orientation.y,
            p.orientation.z,
        ));
        let c = Point3::new(p.position.x, p.position.y, p.position.z);
        let half = q * Vector3::z() * (0.5 * m.scale.z);
        (c - half, c + half)
    }

    #[test]
    fn the_trocar_is_drawn_as_its_model_where_the_estimate_and_the_truth_put_it() {
        let model = TrocarModel::shipped();
        let axis = Vector3::new(0.0, 0.6, -0.8);
        let rotation = nalgebra::UnitQuaternion::rotation_between(&Vector3::z(), &axis).unwrap();
        let at = Isometry3::from_parts(Vector3::new(0.5, -0.1, 0.3).into(), rotation);
        let scene = Scene {
            trocar: Some(at),
            ..unknown()
        };
        let a = docking_markers(rosrust::Time::new(), "lbr_link_0", &scene, &MarkerStyle::default());
        let find = |id: Id| a.markers.iter().find(|m| m.id == id as i32).unwrap();
        let (head, cannula) = (find(Id::TrocarHead), find(Id::TrocarBody));
        let port = Point3::from(at.translation.vector);
        let h = model.head.height;
        // The head from the port's face into the body, the cannula from there on.
        let (top, bottom) = ends(head);
        assert!((top - port).norm() < 1e-12 && (bottom - (port + axis * h)).norm() < 1e-12);
        assert_eq!((head.scale.x, head.scale.z), (2.0 * model.head.radius, h));
        let (top, bottom) = ends(cannula);
        assert!((top - (port + axis * h)).norm() < 1e-12);
        assert!((bottom - (port + axis * (h + model.cannula.length))).norm() < 1e-12);
        assert_eq!(cannula.scale.y, 2.0 * model.cannula.radius);
        // The truth: the same solids where the simulator's trocar is, and the wall across its
        // axis through the fulcrum.
        let truth = Isometry3::from_parts(Vector3::new(0.502, -0.1, 0.3).into(), rotation);
        let fulcrum = Point3::from(truth.translation.vector) + axis * 0.04;
        let t = truth_markers(rosrust::Time::new(), "lbr_link_0", &truth, &fulcrum, &model);
        assert_eq!(t.markers.len(), 3);
        assert!(t
            .markers
            .iter()
            .all(|m| m.ns == "truth" && m.header.frame_id == "lbr_link_0"));
        let (top, _) = ends(&t.markers[0]);
        assert!((top - Point3::from(truth.translation.vector)).norm() < 1e-12);
        assert!(
            (top - port).norm() > 1e-3,
            "the truth is drawn where it is, not at the estimate"
        );
        let (a_side, b_side) = ends(&t.markers[2]);
        assert!((nalgebra::center(&a_side, &b_side) - fulcrum).norm() < 1e-12);
        assert!(((b_side - a_side).normalize() - axis).norm() < 1e-12);
        assert_eq!(t.markers[2].scale.x, WALL_DIAMETER_M);
    }

    /// A scene that knows nothing.
    fn unknown() -> Scene {
        Scene {
            trocar: None,
            goal: None,
            tip: None,
            f_ext: Vector3::zeros(),
            reference: None,
            pivot: None,
        }
    }

    #[test]
    fn the_tip_path_is_a_line_through_its_points_and_nothing_before_two() {
        let style = MarkerStyle::default();
        let pts = [
            Point3::new(0.5, 0.0, 0.3),
            Point3::new(0.52, 0.01, 0.28),
            Point3::new(0.55, 0.0, 0.25),
        ];
        let m = tip_path(crate::ros::convert::ros_time(1.0), "lbr_link_0", pts.iter(), &style);
        assert_eq!(m.type_, visualization_msgs::Marker::LINE_STRIP as i32);
        assert_eq!(
            (m.ns.as_str(), m.action),
            ("dry_run", visualization_msgs::Marker::ADD as i32)
        );
        assert_eq!(m.points.len(), 3);
        assert_eq!((m.points[2].x, m.points[2].z), (0.55, 0.25));
        let one = tip_path(
            crate::ros::convert::ros_time(1.0),
            "lbr_link_0",
            pts[..1].iter(),
            &style,
        );
        assert_eq!(one.action, visualization_msgs::Marker::DELETE as i32);
        assert!(one.points.is_empty());
    }

    #[test]
    fn unknown_geometry_is_deleted() {
        let a = docking_markers(rosrust::Time::new(), "b", &unknown(), &MarkerStyle::default());
        let del = visualization_msgs::Marker::DELETE as i32;
        assert_eq!(a.markers.len(), 12);
        assert!(a.markers.iter().all(|m| m.action == del));
    }

    #[test]
    fn the_fulcrum_and_the_cone_follow_the_pivot() {
        let axis = Vector3::new(0.0, 0.6, -0.8);
        let half = 30f64.to_radians();
        let fulcrum = Point3::new(0.5, -0.1, 0.3);
        let scene = Scene {
            pivot: Some(PivotReport {
                fulcrum,
                shaft_distance: 2e-4,
                lateral_force: 0.3,
                depth: 0.03,
                cone_axis: axis,
                cone_half_angle: half,
                limit: None,
                ignored: None,
                fulcrum_depth: 0.02,
                breathing_offset: 0.0,
            }),
            ..unknown()
        };
        let style = MarkerStyle::default();
        let a = docking_markers(rosrust::Time::new(), "lbr_link_0", &scene, &style);
        let add = visualization_msgs::Marker::ADD as i32;
        let f = a.markers.iter().find(|m| m.id == Id::Fulcrum as i32).unwrap();
        assert_eq!(f.action, add);
        assert_eq!(
            (f.pose.position.x, f.pose.position.y, f.pose.position.z),
            (0.5, -0.1, 0.3)
        );
        let c = a.markers.iter().find(|m| m.id == Id::Cone as i32).unwrap();
        assert!(f.ns == PIVOT_NS && c.ns == PIVOT_NS, "one namespace to toggle in RViz");
        assert_eq!(c.type_, visualization_msgs::Marker::LINE_LIST as i32);
        assert_eq!(c.points.len() % 2, 0, "a line list takes pairs");
        assert_eq!(c.points.len(), 4 * (CONE_RIM + CONE_GENERATORS));
        // Every point but the apex lies on the double cone: at the cone's length from the
        // fulcrum, at the half angle from the axis on one side or the other.
        let (mut inside, mut outside) = (0, 0);
        for p in &c.points {
            let d = Point3::new(p.x, p.y, p.z) - fulcrum;
            if d.norm() < 1e-12 {
                continue;
            }
            assert!((d.norm() - style.cone_length_m).abs() < 1e-9);
            let angle = d.angle(&axis);
            if angle < std::f64::consts::FRAC_PI_2 {
                assert!((angle - half).abs() < 1e-9, "{angle}");
                inside += 1;
            } else {
                assert!((std::f64::consts::PI - angle - half).abs() < 1e-9, "{angle}");
                outside += 1;
            }
        }
        assert_eq!(inside, outside, "both nappes drawn alike");
    }
}
