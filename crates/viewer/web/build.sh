#!/bin/sh
# Builds the browser bundle of `mvsplat360 view` into ../assets/ (committed, so users need no Node):
#   viewer.js                 three.js + Spark + src/*.js, minified (esbuild, versions pinned in package-lock.json)
#   THIRD_PARTY_LICENSES.txt  the licences of every npm package inside viewer.js
# Run after changing src/ or package.json:  sh crates/viewer/web/build.sh
set -eu
cd "$(dirname "$0")"
npm ci --no-audit --no-fund
out=../assets
npx esbuild src/main.js --bundle --minify --format=iife --target=es2020 \
  --legal-comments=none --log-level=warning \
  --banner:js="/* mvsplat360 view: three.js, @sparkjsdev/spark, fflate (MIT); see THIRD_PARTY_LICENSES.txt */" \
  --outfile="$out/viewer.js"
{
  echo "Third-party software bundled in viewer.js (built by crates/viewer/web/build.sh)."
  for pkg in three @sparkjsdev/spark fflate; do
    ver=$(node -p "require('./node_modules/$pkg/package.json').version")
    echo
    echo "================================================================================"
    echo "$pkg $ver"
    echo "================================================================================"
    cat "node_modules/$pkg/LICENSE"
  done
} > "$out/THIRD_PARTY_LICENSES.txt"
ls -l "$out/viewer.js" "$out/THIRD_PARTY_LICENSES.txt"
