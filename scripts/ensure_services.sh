#!/usr/bin/env bash
# Make sure PostgreSQL (127.0.0.1:5432, trust auth for user postgres) and Redis (127.0.0.1:6379) are running,
# installing them with apt when missing and we are root. Also installs chromium for the dashboard browser tests.
set -euo pipefail

PG_PORT=5432
REDIS_PORT=6379
WAIT_S=${ENSURE_SERVICES_WAIT_S:-60}

log() { echo "ensure_services: $*" >&2; }
up() { (exec 3<>"/dev/tcp/127.0.0.1/$1") 2>/dev/null; }
is_root() { [ "$(id -u)" -eq 0 ]; }
apt_updated=0
apt_install() {
  if ! command -v apt-get >/dev/null; then return 1; fi
  if [ "$apt_updated" -eq 0 ]; then DEBIAN_FRONTEND=noninteractive apt-get update -qq || return 1; apt_updated=1; fi
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@"
}

wait_for() {  # port, name
  local i
  for ((i = 0; i < WAIT_S * 2; i++)); do
    if up "$1"; then log "$2 is up on 127.0.0.1:$1"; return 0; fi
    sleep 0.5
  done
  log "ERROR: $2 did not come up on 127.0.0.1:$1 within ${WAIT_S}s"
  return 1
}

start_postgres() {
  local fresh=0
  if [ ! -d /etc/postgresql ] || [ -z "$(ls /etc/postgresql 2>/dev/null)" ]; then
    if ! is_root; then log "ERROR: PostgreSQL is not installed and we are not root: install it, or start it on :$PG_PORT"; exit 1; fi
    log "installing postgresql"
    apt_install postgresql || { log "ERROR: apt-get install postgresql failed"; exit 1; }
    fresh=1
  fi
  local ver
  ver=$(ls /etc/postgresql | sort -V | tail -1)
  local hba="/etc/postgresql/$ver/main/pg_hba.conf"
  if [ "$fresh" -eq 1 ] || ! grep -qE '^host\s+all\s+all\s+127\.0\.0\.1/32\s+trust' "$hba"; then
    if is_root; then
      # Tests and the embedded tools connect as postgres without a password over TCP on loopback only.
      log "configuring trust auth for 127.0.0.1 in $hba"
      sed -i -E 's/^(host\s+all\s+all\s+127\.0\.0\.1\/32\s+)\S+/\1trust/; s/^(local\s+all\s+all\s+)\S+/\1trust/' "$hba"
      grep -qE '^host\s+all\s+all\s+127\.0\.0\.1/32\s+trust' "$hba" || echo "host all all 127.0.0.1/32 trust" >>"$hba"
    fi
  fi
  log "starting PostgreSQL $ver"
  pg_ctlcluster --skip-systemctl-redirect $(ls /etc/postgresql) main start || true
}

start_redis() {
  if ! command -v redis-server >/dev/null; then
    if ! is_root; then log "ERROR: redis-server is not installed and we are not root: install it, or start it on :$REDIS_PORT"; exit 1; fi
    log "installing redis-server"
    apt_install redis-server || { log "ERROR: apt-get install redis-server failed"; exit 1; }
  fi
  mkdir -p /var/lib/redis /var/log/redis 2>/dev/null || true
  log "starting Redis"
  redis-server --daemonize yes --bind 127.0.0.1 -::1 --port 6379 --save "" --appendonly no --dir /var/lib/redis \
    --logfile /var/log/redis/ci.log
}

if up "$PG_PORT"; then log "PostgreSQL already up on 127.0.0.1:$PG_PORT"; else start_postgres; wait_for "$PG_PORT" PostgreSQL; fi
if up "$REDIS_PORT"; then log "Redis already up on 127.0.0.1:$REDIS_PORT"; else start_redis; wait_for "$REDIS_PORT" Redis; fi

if [ ! -x /usr/bin/chromium ]; then
  if is_root; then
    log "installing chromium (dashboard browser tests)"
    apt_install chromium || log "WARNING: could not install chromium; dashboard browser tests will fail"
  else
    log "WARNING: /usr/bin/chromium missing and not root; dashboard browser tests need it"
  fi
fi
