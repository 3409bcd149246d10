//! A `dynamic_reconfigure` server for the controller's live parameters
//! ([`crate::control::live`]), on the standard protocol so that `rqt_reconfigure` and
//! `rosrun dynamic_reconfigure dynparam` work: the service `~set_parameters`
//! (`dynamic_reconfigure/Reconfigure`), and the latched topics `~parameter_descriptions`
//! (`ConfigDescription`: one group `Default`, every parameter a double with its range) and
//! `~parameter_updates` (`Config`: every value, after each accepted change).
//!
//! A request is checked on the service's thread ([`live::propose`]: names, ranges, the whole
//! parameter set valid), then handed to the control loop, which applies it between two
//! steps or refuses it for the phase ([`live::check_phase`]). A refused request is a failed
//! service call with the reason (dynparam prints it), and nothing changes. The parameters
//! are doubles only; a request's bools, ints and strs name no parameter of ours and are
//! refused.

use std::sync::{Arc, Mutex};

use crate::control::live::{self, LiveValues, LIVE_PARAMS};
use crate::control::ControllerParams;
use crate::ros::msgs::dynamic_reconfigure as dr;
use crate::ros::node::{ros_err, NodeError};

/// The name of the one group.
const GROUP: &str = "Default";

/// The values of `v` as a `Config`.
fn config(v: &LiveValues) -> dr::Config {
    dr::Config {
        doubles: LIVE_PARAMS
            .iter()
            .zip(v.0)
            .map(|(d, value)| dr::DoubleParameter {
                name: d.name.into(),
                value,
            })
            .collect(),
        groups: vec![dr::GroupState {
            name: GROUP.into(),
            state: true,
            id: 0,
            parent: 0,
        }],
        ..Default::default()
    }
}

/// The description: every parameter with its range, and `defaults` as the defaults.
pub fn description(defaults: &LiveValues) -> dr::ConfigDescription {
    let bound = |f: fn(&live::LiveParam) -> f64| LiveValues(LIVE_PARAMS.map(|d| f(&d)));
    dr::ConfigDescription {
        groups: vec![dr::Group {
            name: GROUP.into(),
            type_: String::new(),
            parameters: LIVE_PARAMS
                .iter()
                .map(|d| dr::ParamDescription {
                    name: d.name.into(),
                    type_: "double".into(),
                    level: 0,
                    description: format!("{} [{}]", d.description, liveness_text(d.liveness)),
                    edit_method: String::new(),
                })
                .collect(),
            parent: 0,
            id: 0,
        }],
        max: config(&bound(|d| d.max)),
        min: config(&bound(|d| d.min)),
        dflt: config(defaults),
    }
}

/// When a parameter may change, for its description.
fn liveness_text(l: live::Liveness) -> &'static str {
    match l {
        live::Liveness::Live => "live",
        live::Liveness::LowerLive => "lowered live; raised only in IDLE, TARE, APPROACH",
        live::Liveness::Idle => "only in IDLE: from the next start",
    }
}

/// The changes a `Config` request asks for: its doubles; anything else is refused.
pub fn changes(request: &dr::Config) -> Result<Vec<(String, f64)>, String> {
    let other = request
        .bools
        .iter()
        .map(|b| b.name.as_str())
        .chain(request.ints.iter().map(|i| i.name.as_str()))
        .chain(request.strs.iter().map(|s| s.name.as_str()))
        .next();
    if let Some(name) = other {
        return Err(format!("{name} is not a tunable parameter (they are all doubles)"));
    }
    Ok(request.doubles.iter().map(|d| (d.name.clone(), d.value)).collect())
}

/// The running server: dropping it ends the service.
pub struct ReconfigureServer {
    _service: rosrust::Service,
    _descriptions: rosrust::Publisher<dr::ConfigDescription>,
}

/// Serve the live parameters of `params` under the node's private namespace; `apply` hands
/// accepted values to the control loop and returns its reply.
pub fn serve<F>(params: &ControllerParams, apply: F) -> Result<ReconfigureServer, NodeError>
where
    F: Fn(LiveValues) -> Result<String, String> + Send + Sync + 'static,
{
    let values = LiveValues::of(params);
    let mut descriptions = rosrust::publish("~parameter_descriptions", 1).map_err(ros_err)?;
    descriptions.set_latching(true);
    descriptions.send(description(&values)).map_err(ros_err)?;
    let mut updates = rosrust::publish("~parameter_updates", 1).map_err(ros_err)?;
    updates.set_latching(true);
    updates.send(config(&values)).map_err(ros_err)?;
    let state = Arc::new(Mutex::new((params.clone(), updates)));
    let service = rosrust::service::<dr::Reconfigure, _>("~set_parameters", move |req| {
        let mut guard = state.lock().map_err(|e| e.to_string())?;
        let (current, updates) = &mut *guard;
        let result = changes(&req.config)
            .and_then(|c| live::propose(current, &c))
            .and_then(|v| apply(v).map(|reply| (v, reply)));
        match result {
            Ok((v, reply)) => {
                v.write_to(current);
                rosrust::ros_info!("set_parameters: {reply}");
                let now = config(&v);
                let _ = updates.send(now.clone());
                Ok(dr::ReconfigureRes { config: now })
            }
            Err(why) => {
                rosrust::ros_warn!("set_parameters refused: {why}");
                Err(why)
            }
        }
    })
    .map_err(ros_err)?;
    Ok(ReconfigureServer {
        _service: service,
        _descriptions: descriptions,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_description_has_every_parameter_with_its_range_and_default() {
        let p = ControllerParams::default();
        let d = description(&LiveValues::of(&p));
        assert_eq!(d.groups.len(), 1);
        assert_eq!(
            (d.groups[0].name.as_str(), d.groups[0].id, d.groups[0].parent),
            ("Default", 0, 0)
        );
        assert_eq!(d.groups[0].parameters.len(), LIVE_PARAMS.len());
        assert!(d.groups[0].parameters.iter().all(|x| x.type_ == "double"));
        let find = |c: &dr::Config, n: &str| c.doubles.iter().find(|x| x.name == n).map(|x| x.value);
        assert_eq!(find(&d.dflt, "force_stop_n"), Some(p.guard.force_stop_n));
        assert_eq!(find(&d.max, "force_stop_n"), Some(60.0));
        assert_eq!(find(&d.min, "insert_speed_m_s"), Some(0.001));
        assert_eq!(d.dflt.groups[0].name, "Default");
    }

    #[test]
    fn a_request_of_another_type_is_refused() {
        let mut req = dr::Config::default();
        req.doubles.push(dr::DoubleParameter {
            name: "insert_speed_m_s".into(),
            value: 0.02,
        });
        assert_eq!(changes(&req).unwrap(), vec![("insert_speed_m_s".to_string(), 0.02)]);
        req.bools.push(dr::BoolParameter {
            name: "force_feedback".into(),
            value: false,
        });
        let e = changes(&req).unwrap_err();
        assert!(e.contains("force_feedback is not a tunable"), "{e}");
    }
}
