#!/bin/sh
# The database server of compose.facility.yaml: on first start (an empty data folder) a
# cluster whose superuser is POSTGRES_USER with POSTGRES_PASSWORD, and the database
# POSTGRES_DB, as the official image makes them; then the server, on every address, with a
# password (SCRAM) asked of every connection over the network.
set -eu
user=${POSTGRES_USER:-focustrack}
database=${POSTGRES_DB:-$user}
data=/var/lib/postgresql/data
if [ -z "${POSTGRES_PASSWORD:-}" ]; then
    echo "focustrack-postgres: set POSTGRES_PASSWORD (compose: in .env)" >&2
    exit 2
fi
bin=$(ls -d /usr/lib/postgresql/*/bin | sort -V | tail -n 1)
if [ ! -s "$data/PG_VERSION" ]; then
    password_file=$(mktemp)
    printf '%s' "$POSTGRES_PASSWORD" > "$password_file"
    # UTF-8 whatever the image's locale: psycopg reads text from an SQL_ASCII database as bytes
    "$bin/initdb" -D "$data" -U "$user" --pwfile="$password_file" --encoding=UTF8 --locale=C \
        --auth-local=trust --auth-host=scram-sha-256
    rm -f "$password_file"
    echo "host all all all scram-sha-256" >> "$data/pg_hba.conf"
    if [ "$database" != "postgres" ]; then
        echo "CREATE DATABASE \"$database\"" | "$bin/postgres" --single -D "$data" postgres >/dev/null
    fi
fi
exec "$bin/postgres" -D "$data" -c listen_addresses='*' -k /tmp
