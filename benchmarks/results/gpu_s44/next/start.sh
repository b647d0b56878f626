# The lease's start (the last Warp call, after `source .gpu-wp-LAST/activate.sh`): copy the
# tree to /var/tmp/after and start job.sh detached; .gpu-job holds this folder's files.
set -e
mkdir -p /var/tmp/after /var/tmp/res/s45
tar cf - --exclude='./.gpu-wp-*' --exclude='./.gpu-data' --exclude='./.gpu-before' \
    --exclude=./benchmarks/results . | (cd /var/tmp/after && tar xf -)
setsid nohup bash /var/tmp/after/.gpu-job/job.sh > /var/tmp/res/s45-job.log 2>&1 < /dev/null &
sleep 5; cat /var/tmp/res/s45/progress.log; nvidia-smi --query-gpu=name --format=csv,noheader
