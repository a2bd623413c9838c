#!/bin/bash
# Durable upload throughput of mapd in plaintext and with TLS + bearer-token authentication,
# interleaved (8 clients, 2000 passages, scratch databases). Usage: scripts/bench-security.sh [PAIRS]
# Needs a build in ./build and openssl.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
build=$root/build
pairs=${1:-3}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
cd "$work"
ec="-newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes"
{
  openssl req -x509 $ec -keyout ca.key -out ca.pem -days 2 -subj /CN=bench-ca
  openssl req $ec -keyout server.key -out server.csr -subj /CN=localhost
  echo subjectAltName=DNS:localhost,IP:127.0.0.1 > san.ext
  openssl x509 -req -in server.csr -CA ca.pem -CAkey ca.key -CAcreateserial -out server.pem -days 2 -extfile san.ext
} >openssl.log 2>&1
head -c 24 /dev/urandom | base64 > admin.token
echo "sha256:$(tr -d '\n' < admin.token | sha256sum | cut -d' ' -f1) admin bench" > auth

run() {  # run MODE PORT
  local mode=$1 port=$2 server_flags=() client_flags=()
  if [ "$mode" = tls ]; then
    server_flags=(--tls-cert server.pem --tls-key server.key --auth on --auth-file auth)
    client_flags=(--tls-ca ca.pem --token-file admin.token)
  fi
  rm -f "bench-$mode.db"*
  "$build/server/mapd" --listen "127.0.0.1:$port" --db "$work/bench-$mode.db" --log-level warn "${server_flags[@]}" \
    2>"mapd-$mode.log" &
  local pid=$!
  sleep 1.5
  echo -n "$mode: "
  "$build/client/mapsim" bench --server "127.0.0.1:$port" --clients 8 --passages 2000 --readers 1 --seconds 1 \
    "${client_flags[@]}" | head -1
  kill "$pid"
  wait "$pid"
}

for ((i = 0; i < pairs; ++i)); do
  run plain 50191
  run tls 50192
done
