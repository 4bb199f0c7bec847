#!/usr/bin/env bash
# A private CA and certificates for the TLS router, the tracking service and each robot:
#   bash docker/tls/make-certs.sh DIR HOST [ROBOT ...]
# HOST is the router's address as robots dial it (an IP or a DNS name). Keep ca.key offline; give
# each robot its own certificate (its common name is what access-control rules match).
# It also writes DIR/router.json5, the router's config with access control for those robots: a
# robot may send frames and observations, open sessions under its own name, ask the service and
# hear its answers, each on its own sessions' keys alone; only the service's certificate may answer,
# publish estimates or declare the service's liveliness token, and no robot receives another's frames,
# estimates or status. Run it again with every robot to add one.
set -euo pipefail
dir=$1 host=$2
shift 2
robots=("${@:-robot}")
mkdir -p "$dir" && cd "$dir"
if [[ $host =~ ^[0-9.]+$ ]]; then san="IP:$host,DNS:localhost"; else san="DNS:$host,DNS:localhost"; fi
quiet() { "$@" >/dev/null 2>&1 || { "$@"; exit 1; }; }
[[ -f ca.key ]] || quiet openssl req -x509 -newkey rsa:2048 -nodes -keyout ca.key -out ca.crt -days 825 \
    -subj "/CN=inhand-tracker lab CA"
issue() {  # name, extended key usage
    printf 'subjectAltName=%s\nextendedKeyUsage=%s\nbasicConstraints=CA:FALSE\n' "$san" "$2" > "$1.ext"
    quiet openssl req -newkey rsa:2048 -nodes -keyout "$1.key" -out "$1.csr" -subj "/CN=$1"
    quiet openssl x509 -req -in "$1.csr" -CA ca.crt -CAkey ca.key -CAcreateserial -out "$1.crt" -days 825 \
        -extfile "$1.ext"
    rm "$1.csr" "$1.ext"
}
issue router serverAuth
issue inhand-service clientAuth
for robot in "${robots[@]}"; do issue "$robot" clientAuth; done
chmod 600 ./*.key
names=$(printf '"%s", ' "${robots[@]}")
# Each robot opens sessions under its own name only (rpc/open/NAME), and a session opened under a
# name has an id that starts with it (NAME~...): each robot then puts frames and observations,
# holds a liveliness token, asks for estimates and status, and hears them, on its own sessions' keys
# alone. The service's per-peer caps count what each certificate opens; no robot spends another's.
own_rules="" own_subjects="" own_policies=""
for robot in "${robots[@]}"; do
  s="inhand/*/*/s/$robot~\$*"
  own_rules+="      { id: \"own-$robot-sends\", permission: \"allow\", flows: [\"ingress\"], messages: [\"put\"],"
  own_rules+=$'\n'"        key_exprs: [\"$s/frame\", \"$s/observation\"] },"$'\n'
  own_rules+="      { id: \"own-$robot-present\", permission: \"allow\", flows: [\"ingress\"], messages: [\"liveliness_token\"],"
  own_rules+=$'\n'"        key_exprs: [\"$s/robot\"] },"$'\n'
  own_rules+="      { id: \"own-$robot-asks\", permission: \"allow\", flows: [\"ingress\"], messages: [\"query\"],"
  own_rules+=$'\n'"        key_exprs: [\"inhand/*/*/rpc/open/$robot\", \"$s/pose\", \"$s/status\"] },"$'\n'
  own_rules+="      { id: \"own-$robot-hears\", permission: \"allow\", flows: [\"egress\"], messages: [\"put\", \"reply\"],"
  own_rules+=$'\n'"        key_exprs: [\"$s/pose\", \"$s/status\"] },"$'\n'
  own_subjects+="      { id: \"robot-$robot\", cert_common_names: [\"$robot\"] },"$'\n'
  own_policies+="      { id: \"policy-$robot\", rules: [\"own-$robot-sends\", \"own-$robot-present\", \"own-$robot-asks\", \"own-$robot-hears\"],"
  own_policies+=$'\n'"        subjects: [\"robot-$robot\"] },"$'\n'
done
own_rules=${own_rules%$'\n'} own_subjects=${own_subjects%$'\n'} own_policies=${own_policies%$'\n'}
cat > router.json5 <<EOF
// The zenohd router of docker/compose-tls.yml, written by make-certs.sh for: ${robots[*]}.
// The only listening endpoint on the network: TLS with client certificates (mTLS), so only peers
// holding a certificate from the lab's CA connect, and access control by certificate name.
{
  mode: "router",
  listen: { endpoints: ["tls/0.0.0.0:7447"] },
  scouting: { multicast: { enabled: false }, gossip: { enabled: false } },
  transport: {
    link: {
      tls: {
        listen_certificate: "/certs/router.crt",
        listen_private_key: "/certs/router.key",
        root_ca_certificate: "/certs/ca.crt",
        enable_mtls: true,
      },
    },
  },
  access_control: {
    enabled: true,
    default_permission: "deny",
    rules: [
      // what every robot may do: ask the service, close what it opened (signed), and listen
      { id: "robot-asks", permission: "allow", flows: ["ingress"], messages: ["query"],
        key_exprs: ["inhand/*/*/info", "inhand/*/*/rpc/close"] },
      // a robot's publisher sends, and its queries go, only where the service declared a subscriber or
      // a queryable, on s/*/*
      { id: "robot-is-heard", permission: "allow", flows: ["egress"], messages: ["declare_subscriber", "declare_queryable"],
        key_exprs: ["inhand/*/*/s/**"] },
      { id: "robot-listens", permission: "allow", flows: ["ingress"],
        messages: ["liveliness_query", "declare_subscriber", "declare_liveliness_subscriber"],
        key_exprs: ["inhand/**"] },
      // each robot's own sessions (their ids start with its name): what it sends, holds, asks and hears
$own_rules
      // what every robot hears: the service's info, beats, answers to opens and closes, liveliness;
      // never a frame, and another robot's estimates or status never (its own: the rules above)
      { id: "robot-hears", permission: "allow", flows: ["egress"],
        messages: ["put", "reply", "liveliness_token", "declare_queryable", "declare_subscriber",
                   "declare_liveliness_subscriber", "query", "liveliness_query"],
        key_exprs: ["inhand/*/*/alive", "inhand/*/*/info", "inhand/*/*/beat", "inhand/*/*/rpc/**"] },
      { id: "service-all", permission: "allow", flows: ["ingress", "egress"],
        messages: ["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
                   "liveliness_token", "declare_liveliness_subscriber", "liveliness_query"],
        key_exprs: ["inhand/**"] },
    ],
    subjects: [
      { id: "robots", cert_common_names: [${names%, }] },
      { id: "service", cert_common_names: ["inhand-service"] },
$own_subjects
    ],
    policies: [
      { id: "robots", rules: ["robot-asks", "robot-is-heard", "robot-listens", "robot-hears"], subjects: ["robots"] },
$own_policies
      { id: "service", rules: ["service-all"], subjects: ["service"] },
    ],
  },
}
EOF
echo "certificates in $dir: ca.crt, router, inhand-service, ${robots[*]}; router.json5 admits those robots"
