#!/usr/bin/env bash
# Start a throw-away PostgreSQL server for the sweep tests (tests/framework/test_sweeps_postgres.py) and hand over its URL:
#
#   export SB3_TD3X_TEST_PG_URL="$(bash .ci/postgres.sh)"   # run: prints the URL on stdout
#   . .ci/postgres.sh                                        # sourced: exports SB3_TD3X_TEST_PG_URL itself
#
# Installs PostgreSQL from Debian's packages when it is missing, makes a cluster of its own in $PGDATA
# (default /var/tmp/sb3-td3x-postgres), listening on 127.0.0.1:$PGPORT (default 55432) only, with a user and a
# database for the tests, and a second pair for the test of secrets (tests/framework/test_no_secret_in_records.py).
# Idempotent: a second call finds the server running, adds what is missing, and prints the same URL.
# Everything runs in a subshell, so that sourcing this file leaves the caller's shell as it was.
_sb3_td3x_start_postgres() (
  set -euo pipefail

  PGDATA="${SB3_TD3X_PGDATA:-/var/tmp/sb3-td3x-postgres}"
  PGPORT="${SB3_TD3X_PGPORT:-55432}"
  DB_USER=td3x
  DB_PASSWORD=td3x
  DB_NAME=td3x_test
  SECRET_USER=td3x_secret
  SECRET_PASSWORD='p@ss:w/rd%'
  SOCKET_DIR="$PGDATA"

  log() { echo "[postgres.sh] $*" >&2; }

  pg_bin() {
    ls -d /usr/lib/postgresql/*/bin 2>/dev/null | sort -V | tail -n 1
  }

  if [ -z "$(pg_bin)" ]; then
    if [ "$(id -u)" -ne 0 ]; then
      log "PostgreSQL is not installed and this is not root: install the Debian package 'postgresql' first"
      exit 1
    fi
    log "installing PostgreSQL from Debian's packages"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq >&2
    apt-get install -y -qq postgresql >&2
  fi
  BIN="$(pg_bin)"

  # initdb and postgres refuse to run as root: run them as the 'postgres' user the package created.
  if [ "$(id -u)" -eq 0 ]; then
    as_owner() { runuser -u postgres -- "$@"; }
    OWNER=postgres
  else
    as_owner() { "$@"; }
    OWNER="$(id -un)"
  fi

  if [ ! -s "$PGDATA/PG_VERSION" ]; then
    log "creating a cluster in $PGDATA"
    mkdir -p "$PGDATA"
    chown "$OWNER" "$PGDATA"
    chmod 700 "$PGDATA"
    pwfile="$(mktemp)"
    echo postgres >"$pwfile"
    chown "$OWNER" "$pwfile"
    as_owner "$BIN/initdb" -D "$PGDATA" -U postgres --pwfile="$pwfile" --auth-local=trust --auth-host=scram-sha-256 \
      --encoding=UTF8 >&2
    rm -f "$pwfile"
  fi

  if ! as_owner "$BIN/pg_ctl" -D "$PGDATA" status >/dev/null 2>&1; then
    log "starting the server on 127.0.0.1:$PGPORT"
    as_owner "$BIN/pg_ctl" -D "$PGDATA" -l "$PGDATA/server.log" -w -t 60 \
      -o "-p $PGPORT -c listen_addresses=127.0.0.1 -k $SOCKET_DIR -c max_connections=200" start >&2
  fi

  psql_admin() { as_owner "$BIN/psql" -h "$SOCKET_DIR" -p "$PGPORT" -U postgres -d postgres -v ON_ERROR_STOP=1 -qtA "$@"; }
  if [ "$(psql_admin -c "SELECT 1 FROM pg_roles WHERE rolname = '$DB_USER'")" != 1 ]; then
    psql_admin -c "CREATE ROLE $DB_USER LOGIN PASSWORD '$DB_PASSWORD'" >&2
  fi
  if [ "$(psql_admin -c "SELECT 1 FROM pg_database WHERE datname = '$DB_NAME'")" != 1 ]; then
    psql_admin -c "CREATE DATABASE $DB_NAME OWNER $DB_USER" >&2
  fi
  # A second user whose password has the characters a URL must encode, with a database of its own, for
  # tests/framework/test_no_secret_in_records.py (which knows both and reaches them at this server's host and port).
  if [ "$(psql_admin -c "SELECT 1 FROM pg_roles WHERE rolname = '$SECRET_USER'")" != 1 ]; then
    psql_admin -c "CREATE ROLE $SECRET_USER LOGIN PASSWORD '$SECRET_PASSWORD'" >&2
  fi
  if [ "$(psql_admin -c "SELECT 1 FROM pg_database WHERE datname = '$SECRET_USER'")" != 1 ]; then
    psql_admin -c "CREATE DATABASE $SECRET_USER OWNER $SECRET_USER" >&2
  fi

  echo "postgresql://$DB_USER:$DB_PASSWORD@127.0.0.1:$PGPORT/$DB_NAME"
)

if [ "${BASH_SOURCE[0]}" != "$0" ]; then
  SB3_TD3X_TEST_PG_URL="$(_sb3_td3x_start_postgres)" || return 1
  export SB3_TD3X_TEST_PG_URL
else
  _sb3_td3x_start_postgres
fi
