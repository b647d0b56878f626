# detached: bash /var/tmp/after/.gpu-job/job.sh RUNS OUTNAME  (the mask A/B on blocks first, then the list)
cd /var/tmp/after && source /var/tmp/gpu-warp/activate.sh
export PYTHONPATH=/var/tmp/after:${PYTHONPATH:-}
while [ ! -e /var/tmp/data/blocks.ready ]; do sleep 2; done
mkdir -p /var/tmp/res/m
DEVICE=cuda WARMUP=1000 python .gpu-job/mask_ab.py /var/tmp/data/blocks /var/tmp/res/m/ab 2 > /var/tmp/res/m/mask_ab.log 2>&1
touch /var/tmp/res/m/all.done
WAIT_READY=900 bash benchmarks/gpu_runs60.sh /var/tmp/data /var/tmp/res/$2 /var/tmp/after/.gpu-job/$1 "$(cat .gpu-job/COMMIT)" > /var/tmp/res-$2.log 2>&1
