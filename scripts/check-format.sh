#!/usr/bin/env bash
# Every tracked C++ file must be formatted by the project's .clang-format (clang-format 14).
# Prints the files that are not and fails; `clang-format -i FILE` fixes one.
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
cd "$here"
if [ ! -d .git ] && [ ! -f .git ]; then
    echo "check-format: not a git checkout, nothing to check" >&2
    exit 0
fi
bad=()
while IFS= read -r f; do
    if ! clang-format --dry-run --Werror "$f" >/dev/null 2>&1; then
        bad+=("$f")
    fi
done < <(git ls-files '*.cpp' '*.hpp' '*.h')
if ((${#bad[@]})); then
    echo "check-format: ${#bad[@]} file(s) not formatted by .clang-format (run clang-format -i on them):" >&2
    printf '  %s\n' "${bad[@]}" >&2
    exit 1
fi
echo "check-format: every C++ file is formatted"
