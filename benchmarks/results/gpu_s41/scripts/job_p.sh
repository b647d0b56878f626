# detached: bash /var/tmp/after/.gpu-job/job_p.sh RUNS OUTNAME PROFSCENE
# the early-phase profile (plain and refined, --warmup 300) on PROFSCENE, then the list RUNS
cd /var/tmp/after && source /var/tmp/gpu-warp/activate.sh
R=/var/tmp/res/$2; OUT=$R/prof; source benchmarks/gpu_env.sh
while [ ! -e /var/tmp/data/$3.ready ]; do sleep 2; done
for v in 'plain={}' 'ref={"train":{"refine_poses":true}}'; do
  n=${v%%=*}
  timeout 300 $PY -m benchmarks.profile_step --scene /var/tmp/data/$3 --device cuda --warmup 300 \
    --steps 50 --quiet --variant "$v" --out $OUT/$n > $OUT/$n.log 2>&1
  echo "$n rc $?" >> $OUT/progress.log
done
touch $OUT/all.done
WAIT_READY=900 bash benchmarks/gpu_runs60.sh /var/tmp/data $R/runs /var/tmp/after/.gpu-job/$1 "$(cat .gpu-job/COMMIT)" > /var/tmp/res-$2.log 2>&1
