server=$1 cli=$2 port=$3
repo=$(mktemp -d); "$server" --scene-repo "$repo" --seed-samples --address 127.0.0.1:$port > /tmp/vm_$port.log 2>&1 &
spid=$!; sleep 4
start=$(date +%s.%N)
"$cli" --server 127.0.0.1:$port voxelize --scene cornell_box_visq --width 2048 --height 2048 --slices 512 --solid > /tmp/vm_out_$port.txt 2>&1
end=$(date +%s.%N)
echo "$(head -1 /tmp/vm_out_$port.txt); $(echo "$end - $start" | bc) s; server $(grep VmHWM /proc/$spid/status), $(grep VmRSS /proc/$spid/status)"
kill $spid; wait $spid 2>/dev/null; rm -rf "$repo"
