#!/usr/bin/env bash
# Speed–accuracy sweeps of graphs/decompose.ron (see bench/notes/analyze.md). Every row is one
# `ocellus run` with a parameter overridden, 5 repeats; the time is the node's profile median,
# the accuracy the emitted metrics. Run from the repository root:
#     bash bench/decompose_sweep.sh > /tmp/decompose_sweep.md
set -euo pipefail

tmp=$(mktemp -d)
run() { # OUTPUT NODES... -- SET...
    local output=$1; shift
    cargo run --release -q -- run graphs/decompose.ron --threads 2 --repeat 5 \
        --profile "$tmp/p.json" --emit "$tmp/e" --output "$output" "$@" > /dev/null
}
ms() { python3 -c "import json,sys; p=json.load(open('$tmp/p.json'))['nodes']; print(' + '.join(f\"{p[n]['median_ms']:.2f}\" for n in sys.argv[1:]))" "$@"; }
metric() { python3 -c "import json,sys; m=json.load(open('$tmp/e/$1.json')); print(' | '.join(f'{m.get(k, float(\"inf\")):.4g}' for k in sys.argv[1:]))" "${@:2}"; }

echo "### PCA (40 faces 32×32): components vs reconstruction error and time"
echo "| components | explained variance | rmse | PSNR dB | analyze.pca ms |"
echo "|---|---|---|---|---|"
for k in 1 2 4 8 16 24 39; do
    run pca --set eigen.components=$k
    echo "| $k | $(metric pca explained_variance rmse psnr_db) | $(ms eigen) |"
done

echo; echo "### SVD (gray test card 128×96): rank vs PSNR and storage"
echo "| rank | storage ratio | relative Frobenius error | PSNR dB | analyze.svd_compress ms |"
echo "|---|---|---|---|---|"
for k in 1 2 4 8 12 16 32 64 96; do
    run svd --set low_rank.rank=$k
    echo "| $k | $(metric svd storage_ratio relative_frobenius_error psnr_db) | $(ms low_rank) |"
done

echo; echo "### Radon + FBP (phantom 96×96, Hann window): angles vs PSNR and time"
echo "| angles | PSNR dB | SSIM | radon ms + fbp ms |"
echo "|---|---|---|---|"
for a in 10 20 45 90 180 360; do
    run fbp_score --set sino.angles=$a
    echo "| $a | $(metric fbp_score psnr_db ssim) | $(ms sino recon) |"
done
echo; echo "| window (180 angles) | PSNR dB | SSIM | fbp ms |"
echo "|---|---|---|---|"
for f in ram_lak shepp_logan cosine hamming hann; do
    run fbp_score --set sino.angles=180 --set recon.filter=$f
    echo "| $f | $(metric fbp_score psnr_db ssim) | $(ms recon) |"
done

echo; echo "### k-means colour quantization (RGB test card 128×96): k vs PSNR and time"
echo "| k | PSNR dB | SSIM | segment.kmeans ms |"
echo "|---|---|---|---|"
for k in 2 4 8 16 32 64; do
    run quant_score --set quant.k=$k
    echo "| $k | $(metric quant_score psnr_db ssim) | $(ms quant) |"
done
rm -rf "$tmp"
