#!/usr/bin/env bash
# Renders visq.conf.template: render.sh PREFIX_DIR LISTEN REPLICA... > nginx.conf
# e.g. render.sh /tmp/visq-nginx 127.0.0.1:50050 127.0.0.1:50061 127.0.0.1:50062
set -euo pipefail
prefix=$1 listen=$2
shift 2
replicas=""
for r in "$@"; do replicas+="    server $r max_fails=1 fail_timeout=5s;"$'\n'; done
template="$(dirname "$0")/visq.conf.template"
mkdir -p "$prefix"
awk -v prefix="$prefix" -v listen="$listen" -v replicas="$replicas" '
  { gsub(/@PREFIX@/, prefix); gsub(/@LISTEN@/, listen);
    if ($0 ~ /@REPLICAS@/) { printf "%s", replicas; next } print }' "$template"
