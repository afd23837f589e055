#!/usr/bin/env bash
# make reproduction-docs: docs/reproduction.md, docs/reproduction-family.md and their
# figures (docs/reproduction/) from the three studies' directories, without running an
# experiment.  Every input is checked first: when one is missing the tree is left exactly
# as it is (one line on stderr naming what is missing, exit 2).  The new files are built
# beside the old ones and moved into place only once all of them are complete.
#
#   tools/reproduction_docs.sh STUDY_OUT BENCH_OUT FAMILY_OUT
set -euo pipefail
if [ $# -ne 3 ]; then
    echo 'usage: tools/reproduction_docs.sh STUDY_OUT BENCH_OUT FAMILY_OUT' >&2
    exit 2
fi
study=$1 bench=$2 family=$3
missing=()
for f in "$study/tables.png" "$study/convergence.png" "$study/comparison.png" \
         "$study/reproduction.md" "$bench/beside.md" "$family/family.md"; do
    [ -f "$f" ] || missing+=("$f")
done
shopt -s nullglob
drives=("$family"/*/comparison.png)
[ ${#drives[@]} -gt 0 ] || missing+=("$family/<drive>/comparison.png")
if [ ${#missing[@]} -gt 0 ]; then
    echo "error: reproduction-docs: missing ${missing[*]} (run make reproduction first); docs/ left unchanged" >&2
    exit 2
fi

new=$(mktemp -d docs/.reproduction-new.XXXXXX)
trap 'rm -rf "$new"' EXIT
mkdir -p "$new/reproduction/family"
cp "$study/tables.png" "$study/convergence.png" "$study/comparison.png" "$new/reproduction/"
for png in "${drives[@]}"; do
    d=$(basename "$(dirname "$png")")
    mkdir -p "$new/reproduction/family/$d"
    cp "$png" "$new/reproduction/family/$d/"
done
{
    sed -e 's#](tables.png)#](reproduction/tables.png)#' \
        -e 's#](convergence.png)#](reproduction/convergence.png)#' \
        -e 's#](comparison.png)#](reproduction/comparison.png)#' \
        "$study/reproduction.md"
    cat "$bench/beside.md"
    echo
    echo '## The study over a family of drives'
    echo
    echo 'Every algorithm and the Py-BOBYQA reference on each drive of the family on the `bench` profile, the summary over the drives and the default against its goal: [reproduction-family.md](reproduction-family.md).'
} > "$new/reproduction.md"
sed -e 's#](\([^)/]*\)/\([a-z_]*\).png)#](reproduction/family/\1/\2.png)#' \
    "$family/family.md" > "$new/reproduction-family.md"

# everything is built: swap it in
rm -rf docs/reproduction
mv "$new/reproduction" docs/reproduction
mv "$new/reproduction.md" docs/reproduction.md
mv "$new/reproduction-family.md" docs/reproduction-family.md
