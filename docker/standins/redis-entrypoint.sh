#!/bin/sh
# The official redis image's entrypoint, less its switch to the redis user: options alone run redis-server, and
# redis-server without a config file that sets protected-mode runs with `--protected-mode no`, since in a
# container other containers are the clients (protected mode refuses every client but loopback's).
set -e
if [ "${1#-}" != "$1" ] || [ "${1%.conf}" != "$1" ]; then
  set -- redis-server "$@"
fi
if [ "$1" = redis-server ]; then
  protected=1
  config=
  if [ -f "${2:-}" ]; then
    config=$2
    grep -q '^protected-mode' "$config" && protected=
  fi
  if [ -n "$protected" ]; then
    shift
    [ -n "$config" ] && shift
    set -- --protected-mode no "$@"
    [ -n "$config" ] && set -- "$config" "$@"
    set -- redis-server "$@"
  fi
fi
exec "$@"
