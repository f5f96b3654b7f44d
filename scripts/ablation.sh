#!/usr/bin/env bash
# The thesis' comparison on our data: one 1000-frame subset, three task sets.
# The README table: EPOCHS=3, the three runs in parallel at one thread each.
set -e
EPOCHS=${EPOCHS:-3}
for spec in "multitask:box,shape,cls" "detonly:box,cls" "shapeonly:shape"; do
  name=${spec%%:*}; tasks=${spec#*:}
  shape-detector train --data data/train --val-data data/val --out runs/cmp_$name --seed 0 \
    --max-frames 1000 --epochs "$EPOCHS" --tasks "$tasks" --device cpu --threads 1 > runs/cmp_$name.log 2>&1
done
