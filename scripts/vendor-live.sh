#!/usr/bin/env bash
# The live page's JavaScript libraries (three.js, uPlot), from the npm registry at the versions
# softphantom/viz/live/static/vendor/package-lock.json pins, bundled by esbuild (pinned too) into
# one minified ES module beside it. The bundle is committed, so a clone, a wheel and the page
# need neither node nor the network; run this only to refresh or check it (node >= 18 and npm).
#   bash scripts/vendor-live.sh           rebuild from the lock, write the vendor files
#   bash scripts/vendor-live.sh --check   rebuild from the lock, fail if the committed files differ
#   bash scripts/vendor-live.sh --update  re-resolve package.json (after editing a version), rewrite the lock too
set -euo pipefail
cd "$(dirname "$0")/.."
mode=${1:-}
case "$mode" in ""|--check|--update) ;; *) echo "usage: $0 [--check|--update]" >&2; exit 2 ;; esac
V=softphantom/viz/live/static/vendor
FILES=(live-libs.min.js uPlot.min.css LICENSE-three.txt LICENSE-uplot.txt SHA256SUMS)
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
cp "$V/package.json" "$V/package-lock.json" "$V/entry.js" "$work/"
cd "$work"
if [ "$mode" = --update ]; then
  npm install --ignore-scripts --no-audit --no-fund --loglevel=error
else
  npm ci --ignore-scripts --no-audit --no-fund --loglevel=error
fi
version() { node -p "require('./node_modules/$1/package.json').version"; }
three=$(version three)
uplot=$(version uplot)
mkdir out
./node_modules/.bin/esbuild entry.js --bundle --format=esm --minify --target=es2020 --legal-comments=eof \
  --banner:js="/* three@$three, uplot@$uplot (MIT: LICENSE-three.txt, LICENSE-uplot.txt); built by scripts/vendor-live.sh from entry.js */" \
  --outfile=out/live-libs.min.js --log-level=warning
cp node_modules/uplot/dist/uPlot.min.css out/
cp node_modules/three/LICENSE out/LICENSE-three.txt
cp node_modules/uplot/LICENSE out/LICENSE-uplot.txt
(cd out && sha256sum live-libs.min.js uPlot.min.css LICENSE-three.txt LICENSE-uplot.txt > SHA256SUMS)
cd - >/dev/null
if [ "$mode" = --check ]; then
  for f in "${FILES[@]}"; do
    cmp -s "$work/out/$f" "$V/$f" || { echo "vendor-live: $V/$f differs from a rebuild from the lock" >&2; exit 1; }
  done
  echo "vendor-live: $V matches three@$three, uplot@$uplot"
  exit 0
fi
for f in "${FILES[@]}"; do cp "$work/out/$f" "$V/$f"; done
[ "$mode" = --update ] && cp "$work/package-lock.json" "$V/package-lock.json"
echo "vendor-live: wrote $V (three@$three, uplot@$uplot)"
