set -e
mkdir -p /var/tmp/after /var/tmp/res
tar cf - --exclude='./.gpu-warp*' --exclude='./.gpu-data' --exclude=./benchmarks/results . | (cd /var/tmp/after && tar xf -)
RNAME=k3 setsid nohup bash /var/tmp/after/.gpu-job/job35b.sh > /var/tmp/res/k3.out 2>&1 < /dev/null &
sleep 3; ls /var/tmp/res; nvidia-smi --query-gpu=name --format=csv,noheader
