#!/usr/bin/env bash
# The thesis' comparison on our data: same subset, same budget, three task sets.
set -e
for spec in "multitask:box,shape,cls" "detonly:box,cls" "shapeonly:shape"; do
  name=${spec%%:*}; tasks=${spec#*:}
  shape-detector train --data data/train --val-data data/val --out runs/abl_$name --seed 0 \
    --max-frames 1000 --epochs 5 --tasks $tasks --device cpu --threads 1 > runs/abl_$name.log 2>&1
done
