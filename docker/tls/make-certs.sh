#!/usr/bin/env bash
# A private CA and certificates for the TLS router, the tracking service and each robot:
#   bash docker/tls/make-certs.sh DIR HOST [ROBOT ...]
# HOST is the router's address as robots dial it (an IP or a DNS name). Keep ca.key offline; give
# each robot its own certificate (its common name is what access-control rules match).
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
echo "certificates in $dir: ca.crt, router, inhand-service, ${robots[*]}"
