# copy the tree to /var/tmp/after and start the list detached: bash .gpu-job/start.sh RUNS OUTNAME
set -e
mkdir -p /var/tmp/after /var/tmp/res
tar cf - --exclude='./.gpu-warp*' --exclude='./.gpu-data' --exclude=./benchmarks/results . | (cd /var/tmp/after && tar xf -)
setsid nohup bash /var/tmp/after/.gpu-job/job.sh "$1" "$2" > /dev/null 2>&1 < /dev/null &
sleep 3; ls /var/tmp/res; nvidia-smi --query-gpu=name --format=csv,noheader
