#!/usr/bin/env bash
# Stages target/dist/esa-server (cargo build --profile dist -p esa-server) and exactly the shared
# libraries ldd lists for it into deploy/container/rootfs/, then builds the FROM scratch image
# with podman (or buildah). Usage: deploy/container/build.sh [IMAGE]  (default
# localhost/esa-server:<workspace version>). Set ESA_SERVER_BIN to stage another binary.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
repo="$(cd "$here/../.." && pwd)"
version="$(sed -n '/^\[workspace.package\]/,/^\[/s/^version = "\(.*\)"/\1/p' "$repo/Cargo.toml")"
image="${1:-localhost/esa-server:$version}"
binary="${ESA_SERVER_BIN:-$repo/target/dist/esa-server}"
if [[ -z "${ESA_SERVER_BIN:-}" ]]; then
    # The image serves Zenoh (EXPOSE 7447) whatever esa-server's default features are.
    (cd "$repo" && cargo build --profile dist -p esa-server --features zenoh)
fi

rootfs="$here/rootfs"
rm -rf "$rootfs"
install -D -m 755 "$binary" "$rootfs/usr/local/bin/esa-server"
# Every library the dynamic linker resolves (and the loader itself), at the same path.
ldd "$binary" | awk '/=> \//{print $3} /^[[:space:]]*\/.*ld-linux/{print $1}' | while read -r lib; do
    install -D -m 755 "$(readlink -f "$lib")" "$rootfs$lib"
done
mkdir -p "$rootfs/etc" "$rootfs/tmp"
chmod 1777 "$rootfs/tmp"
echo "nonroot:x:65532:65532:esa-server:/nonexistent:/sbin/nologin" > "$rootfs/etc/passwd"
echo "nonroot:x:65532:" > "$rootfs/etc/group"

if command -v podman > /dev/null; then
    builder=(podman build)
else
    builder=(buildah bud)
fi
"${builder[@]}" --label "org.opencontainers.image.version=$version" \
    --label "org.opencontainers.image.licenses=Apache-2.0" \
    --label "org.opencontainers.image.source=https://github.com/esa-rl/esa" \
    -t "$image" -f "$here/Containerfile" "$here"
echo "built $image"
