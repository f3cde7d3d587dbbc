//! Binding robot ids to TLS certificates with Zenoh's access control.
//!
//! Mutual TLS proves that a peer holds a certificate of the fleet's CA, but any such
//! peer can still put on `fleet/<fleet>/<another robot>/...`: the robot id is only a
//! key segment. The access-control block made here closes that. A link is let in
//! only what its certificate's common name entitles it to: robot N's data and
//! presence only from the certificate named for N, and subscriptions only from the
//! fleet's certificates. Everything else, other fleets' keys included, is denied.
//!
//! Zenoh decides per link (`transport.get_auth_ids()`), so this holds in peer mode,
//! where every message comes straight from its sender. Behind a Zenoh router the
//! agents see the router's certificate, not the sender's: the router must check
//! instead ([`AclRole::Router`], printed by `agent acl`).

use super::TransportError;
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use std::collections::BTreeSet;

/// At most this many robots in one access-control block (each adds a rule, a
/// subject and a policy that Zenoh checks per message).
pub const MAX_ROBOTS: usize = 4096;

/// Which robots a fleet has and how their certificates are named.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RobotCertificates {
    /// The fleet's robot ids, the same list in every agent.
    pub robots: Vec<u32>,
    /// The common name (CN) of robot N's certificate: this text with N in place of
    /// `{id}`. Default `robot{id}` (robot 3: `CN=robot3`).
    #[serde(default = "default_common_name")]
    pub common_name: String,
    /// Certificate common names of Zenoh routers (between sites) trusted to forward
    /// every robot's messages: they check the senders' names themselves (their
    /// configuration from `agent acl`). Default none.
    #[serde(default)]
    pub trusted_routers: Vec<String>,
}

fn default_common_name() -> String {
    "robot{id}".to_owned()
}

/// Who enforces the block.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AclRole {
    /// An agent in peer mode: it sends only its own robot's keys.
    Agent(u32),
    /// A Zenoh router between sites: it forwards every robot's keys.
    Router,
}

impl RobotCertificates {
    /// Robot `id`'s certificate common name.
    pub fn name_of(&self, id: u32) -> String {
        self.common_name.replace("{id}", &id.to_string())
    }

    /// Checks that the names are usable: some robots, none twice, not too many, and
    /// a name pattern that tells robots apart.
    pub fn validate(&self) -> Result<(), String> {
        if self.robots.is_empty() {
            return Err("robot_certificates.robots is empty: no robot could send".into());
        }
        if self.robots.len() > MAX_ROBOTS {
            return Err(format!(
                "robot_certificates.robots lists {} robots, more than {MAX_ROBOTS}",
                self.robots.len()
            ));
        }
        let distinct: BTreeSet<u32> = self.robots.iter().copied().collect();
        if distinct.len() != self.robots.len() {
            return Err("robot_certificates.robots lists a robot id twice".into());
        }
        if self.trusted_routers.iter().any(|r| r.is_empty()) {
            return Err("robot_certificates.trusted_routers has an empty name".into());
        }
        let is_router = |id: u32| self.trusted_routers.contains(&self.name_of(id));
        if let Some(&id) = self.robots.iter().find(|&&id| is_router(id)) {
            return Err(format!(
                "robot {id}'s certificate name {:?} is also a trusted router's",
                self.name_of(id)
            ));
        }
        if !self.common_name.contains("{id}") {
            return Err(format!(
                "robot_certificates.common_name {:?} has no {{id}}: every robot would have \
                 the same certificate name, so one could send as another",
                self.common_name
            ));
        }
        Ok(())
    }
}

/// Zenoh's `access_control` block for `fleet_id`, enforced by `role`.
pub fn access_control(
    fleet_id: &str,
    certs: &RobotCertificates,
    role: AclRole,
) -> Result<Value, TransportError> {
    let invalid = |reason: String| TransportError::Config {
        path: "robot_certificates".to_owned(),
        reason,
    };
    certs.validate().map_err(invalid)?;
    if let AclRole::Agent(me) = role {
        if !certs.robots.contains(&me) {
            return Err(invalid(format!(
                "this agent's robot id {me} is not among robot_certificates.robots \
                 {:?}: its peers would refuse everything it sends",
                certs.robots
            )));
        }
    }
    let fleet = format!("fleet/{fleet_id}");
    // What a link may send us (ingress) or be sent (egress) beside data: interest in
    // the fleet's keys and presence, from the fleet's own certificates only.
    let mut rules = vec![
        json!({
            "id": "fleet-subscriptions",
            "permission": "allow",
            "flows": ["ingress", "egress"],
            "messages": ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"],
            "key_exprs": [format!("{fleet}/**")],
        }),
        json!({
            "id": "send",
            "permission": "allow",
            "flows": ["egress"],
            "messages": ["put", "delete", "liveliness_token"],
            "key_exprs": [match role {
                AclRole::Agent(me) => format!("{fleet}/{me}/**"),
                AclRole::Router => format!("{fleet}/**"),
            }],
        }),
    ];
    let members = (certs.robots.iter().map(|&id| certs.name_of(id)))
        .chain(certs.trusted_routers.iter().cloned())
        .collect::<Vec<_>>();
    let mut subjects = vec![json!({ "id": "fleet", "cert_common_names": members })];
    let mut policies = vec![json!({
        "id": "fleet",
        "rules": ["fleet-subscriptions", "send"],
        "subjects": ["fleet"],
    })];
    // A trusted router brings every robot's messages (it checked their senders).
    if !certs.trusted_routers.is_empty() {
        rules.push(json!({
            "id": "forwarded",
            "permission": "allow",
            "flows": ["ingress"],
            "messages": ["put", "delete", "liveliness_token"],
            "key_exprs": [format!("{fleet}/**")],
        }));
        subjects.push(json!({ "id": "routers", "cert_common_names": certs.trusted_routers }));
        policies.push(json!({ "id": "routers", "rules": ["forwarded"], "subjects": ["routers"] }));
    }
    // Robot N's data and presence come in only from the certificate named for N.
    for &id in &certs.robots {
        let name = format!("robot-{id}");
        rules.push(json!({
            "id": name,
            "permission": "allow",
            "flows": ["ingress"],
            "messages": ["put", "delete", "liveliness_token"],
            "key_exprs": [format!("{fleet}/{id}/**")],
        }));
        subjects.push(json!({ "id": name, "cert_common_names": [certs.name_of(id)] }));
        policies.push(json!({ "id": name, "rules": [name], "subjects": [name] }));
    }
    Ok(json!({
        "enabled": true,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn certs(robots: &[u32]) -> RobotCertificates {
        RobotCertificates {
            robots: robots.to_vec(),
            common_name: default_common_name(),
            trusted_routers: Vec::new(),
        }
    }

    #[test]
    fn robot_n_may_send_only_under_its_own_key() -> Result<(), TransportError> {
        let acl = access_control("euroc", &certs(&[0, 1, 2]), AclRole::Agent(1))?;
        let rules = acl["rules"]
            .as_array()
            .map(Vec::as_slice)
            .unwrap_or_default();
        let rule = |id: &str| rules.iter().find(|r| r["id"] == id).cloned();
        assert_eq!(acl["default_permission"], "deny");
        assert_eq!(
            rule("robot-2").map(|r| r["key_exprs"].clone()),
            Some(json!(["fleet/euroc/2/**"]))
        );
        assert_eq!(
            rule("send").map(|r| r["key_exprs"].clone()),
            Some(json!(["fleet/euroc/1/**"]))
        );
        let subjects = acl["subjects"]
            .as_array()
            .map(Vec::as_slice)
            .unwrap_or_default();
        let robot2 = subjects.iter().find(|s| s["id"] == "robot-2");
        assert_eq!(
            robot2.map(|s| s["cert_common_names"].clone()),
            Some(json!(["robot2"]))
        );
        Ok(())
    }

    #[test]
    fn the_block_is_one_zenoh_accepts() -> Result<(), Box<dyn std::error::Error + Send + Sync>> {
        let with_router = RobotCertificates {
            trusted_routers: vec!["site-a".into()],
            ..certs(&[7, 8])
        };
        for role in [AclRole::Agent(7), AclRole::Router] {
            let acl = access_control("f", &with_router, role)?;
            let mut config = zenoh::Config::default();
            config.insert_json5("access_control", &acl.to_string())?;
        }
        Ok(())
    }

    #[test]
    fn unusable_names_are_refused_with_the_reason() {
        let bad = [
            (certs(&[]), "empty"),
            (certs(&[1, 1]), "twice"),
            (
                RobotCertificates {
                    robots: vec![1, 2],
                    common_name: "robot".into(),
                    trusted_routers: Vec::new(),
                },
                "no {id}",
            ),
            (
                RobotCertificates {
                    trusted_routers: vec!["robot2".into()],
                    ..certs(&[1, 2])
                },
                "also a trusted router",
            ),
        ];
        for (c, why) in bad {
            match access_control("f", &c, AclRole::Router) {
                Err(e) => assert!(e.to_string().contains(why), "{e}"),
                Ok(_) => panic!("{c:?} accepted"),
            }
        }
        match access_control("f", &certs(&[1, 2]), AclRole::Agent(3)) {
            Err(e) => assert!(e.to_string().contains("not among"), "{e}"),
            Ok(_) => panic!("an agent outside the list accepted"),
        }
    }
}
