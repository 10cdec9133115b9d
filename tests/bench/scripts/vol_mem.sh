server=$1 cli=$2 port=$3
repo=$(mktemp -d); "$server" --scene-repo "$repo" --seed-samples --address 127.0.0.1:$port > /tmp/volm_$port.log 2>&1 &
spid=$!; sleep 4
"$cli" --server 127.0.0.1:$port volumetric --scene cornell_box_visq --camera 0,1,3.5 --forward 0,0,-1 --sun 0.3,-0.6,-1 --width 4096 --height 4096 --shadow-map 1024 --scattering 0.2 --extinction 0.2 --combined > /dev/null 2>&1
echo "server $(grep VmHWM /proc/$spid/status), $(grep VmRSS /proc/$spid/status)"
kill $spid; wait $spid 2>/dev/null; rm -rf "$repo"
