# Sourced by every script in scripts/: `-h`/`--help` (before any `--`) prints the script's own usage, the
# comment at its top, and ends it, before it sets anything up or runs anything.
#   script_help "$0" "USAGE" "$@"     a script whose options are all its own
#   script_help "$0" "USAGE" "${1:-}" a script whose later arguments belong to a command it runs
script_help() {
    local script=$1 usage=$2
    shift 2
    for arg in "$@"; do
        [ "$arg" = "--" ] && return 0
        if [ "$arg" = "-h" ] || [ "$arg" = "--help" ]; then
            echo "usage: bash scripts/$(basename "$script") $usage"
            echo
            # the header comment, from the line after the shebang to the first line that is not a comment
            sed -n '2,/^[^#]/p' "$script" | sed -n 's/^# \{0,1\}//p'
            exit 0
        fi
    done
}

# A bring-up script's help is its Python module's (every option with its default), under the script's name;
# before set-up (no .venv yet) the header comment stands in for it.
#   module_help "$0" MODULE "USAGE" "$@"
module_help() {
    local script=$1 module=$2 usage=$3 root
    root=$(cd "$(dirname "$script")/.." && pwd)
    shift 3
    for arg in "$@"; do
        [ "$arg" = "--" ] && return 0
        if [ "$arg" = "-h" ] || [ "$arg" = "--help" ]; then
            if [ -x "$root/.venv/bin/python" ]; then
                MORPH_PROG="bash scripts/$(basename "$script")" exec "$root/.venv/bin/python" -m "$module" --help
            fi
            script_help "$script" "$usage" --help
        fi
    done
}
