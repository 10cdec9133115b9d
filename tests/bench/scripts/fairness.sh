#!/usr/bin/env bash
# fairness.sh SERVER_BINARY CLI_BINARY PORT: how long a small hidden-sample
# map waits while a long rendering / voxelization holds the GPU.
server=$1 cli=$2 port=$3
repo=$(mktemp -d); "$server" --scene-repo "$repo" --seed-samples --address 127.0.0.1:$port > /tmp/fair_$port.log 2>&1 &
spid=$!; sleep 4
small() { /usr/bin/time -f "%e" "$cli" --server 127.0.0.1:$port hidden-map --scene cornell_box_visq \
  --source "-0.25,1.99,-0.25;0.5,0,0;0,0,0.5" --receiver "-0.999,0.001,-0.999;1.998,0,0;0,0,1.998" \
  --width 8 --height 8 --samples 16 2>&1 >/dev/null | tail -1; }
echo "small map alone: $(small) s"
for heavy in "volumetric --scene cornell_box_visq --camera 0,1,3.5 --forward 0,0,-1 --sun 0.3,-0.6,-1 --width 4096 --height 4096 --shadow-map 4096 --scattering 0.2 --extinction 0.2 --method ray-marching" \
             "voxelize --scene cornell_box_visq --width 4096 --height 4096 --slices 512 --conservative"; do
  start=$(date +%s.%N)
  "$cli" --server 127.0.0.1:$port $heavy > /dev/null 2>&1 &
  hpid=$!; sleep 2
  s=$(small); wait $hpid; end=$(date +%s.%N)
  echo "${heavy%% *}: heavy call $(echo "$end - $start" | bc) s; small map issued 2 s in waited $s s"
done
kill $spid; wait $spid 2>/dev/null; rm -rf "$repo"
