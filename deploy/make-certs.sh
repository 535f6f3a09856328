#!/bin/sh
# Generate the TLS material of a geocoder Dask cluster with openssl.
#
#   deploy/make-certs.sh [-f] DIR
#
# Writes into DIR (created if missing):
#   ca.pem, ca-key.pem                    a private certificate authority for this cluster only
#   scheduler.pem, scheduler-key.pem      \
#   worker.pem, worker-key.pem             > EC P-256 keys with certificates signed by the CA
#   client.pem, client-key.pem            /
#
# Certificates are valid for 365 days (GEOCODER_CERT_DAYS overrides). Each leaf carries the
# subject alternative names localhost, 127.0.0.1, scheduler, worker and notebook (the compose
# service names) plus every name in GEOCODER_CERT_SANS (comma or space separated; entries that
# look like IPv4/IPv6 addresses become IP SANs, the rest DNS SANs), e.g.
#   GEOCODER_CERT_SANS="geocoder-scheduler,dask.example.org,10.0.0.5" deploy/make-certs.sh certs
# Dask itself authenticates by the CA (mutual TLS, hostnames are not checked); the SANs let
# other TLS clients verify the scheduler by name.
#
# Existing material is kept (the script says so and exits 0) unless -f is given, so a one-shot
# container may run it on every start. Keys are written 0600: keep ca-key.pem off the cluster.
# geocoder/certs.py writes the same file names from Python.
set -eu

usage() {
    echo "usage: $0 [-f] DIR" >&2
    exit 2
}

force=0
if [ "${1:-}" = "-f" ]; then
    force=1
    shift
fi
[ $# -eq 1 ] || usage
dir=$1
days=${GEOCODER_CERT_DAYS:-365}
roles="scheduler worker client"

command -v openssl >/dev/null 2>&1 || {
    echo "make-certs.sh: openssl not found" >&2
    exit 1
}

mkdir -p "$dir"
if [ "$force" -eq 0 ] && [ -s "$dir/ca.pem" ] && [ -s "$dir/client-key.pem" ]; then
    echo "make-certs.sh: TLS material already in $dir (use -f to replace it)"
    exit 0
fi

sans="DNS:localhost,IP:127.0.0.1,DNS:scheduler,DNS:worker,DNS:notebook"
for name in $(printf '%s' "${GEOCODER_CERT_SANS:-}" | tr ',' ' '); do
    if printf '%s' "$name" | grep -Eq '^[0-9]+\.[0-9]+\.[0-9]+\.[0-9]+$|:'; then
        sans="$sans,IP:$name"
    else
        sans="$sans,DNS:$name"
    fi
done

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
trap 'exit 1' INT TERM
umask 077

newkey() {
    openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null
}

# Certificate authority.
newkey "$work/ca-key.pem"
cat >"$work/ca.ext" <<EOF
basicConstraints = critical, CA:TRUE, pathlen:0
keyUsage = critical, keyCertSign, cRLSign
subjectKeyIdentifier = hash
EOF
openssl req -new -key "$work/ca-key.pem" -subj "/O=geocoder/CN=geocoder cluster CA" -out "$work/ca.csr"
openssl x509 -req -in "$work/ca.csr" -signkey "$work/ca-key.pem" -days "$days" -sha256 \
    -extfile "$work/ca.ext" -out "$work/ca.pem" 2>/dev/null

# Leaves: every role acts as TLS server and client (workers talk to each other and the
# scheduler connects back to workers), so each certificate allows both.
cat >"$work/leaf.ext" <<EOF
basicConstraints = critical, CA:FALSE
keyUsage = critical, digitalSignature, keyAgreement
extendedKeyUsage = serverAuth, clientAuth
subjectKeyIdentifier = hash
authorityKeyIdentifier = keyid
subjectAltName = $sans
EOF
for role in $roles; do
    newkey "$work/$role-key.pem"
    openssl req -new -key "$work/$role-key.pem" -subj "/O=geocoder/CN=geocoder $role" -out "$work/$role.csr"
    openssl x509 -req -in "$work/$role.csr" -CA "$work/ca.pem" -CAkey "$work/ca-key.pem" \
        -set_serial "0x$(openssl rand -hex 16)" -days "$days" -sha256 -extfile "$work/leaf.ext" \
        -out "$work/$role.pem" 2>/dev/null
    openssl verify -CAfile "$work/ca.pem" "$work/$role.pem" >/dev/null
done

for f in ca ca-key scheduler scheduler-key worker worker-key client client-key; do
    cp "$work/$f.pem" "$dir/$f.pem"
    case $f in
        *-key) chmod 600 "$dir/$f.pem" ;;
        *) chmod 644 "$dir/$f.pem" ;;
    esac
done
echo "make-certs.sh: wrote CA and scheduler/worker/client certificates to $dir (SANs: $sans)"
