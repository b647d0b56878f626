# bash .gpu-job/carry_thr.sh : copy the carried .gpu-data/thr/* level scenes in and mark them ready
set -e; mkdir -p /var/tmp/thrdata
for d in .gpu-data/thr/*/; do n=$(basename $d); [ -e /var/tmp/thrdata/$n.ready ] && continue
  cp -r $d /var/tmp/thrdata/ && touch /var/tmp/thrdata/$n.ready && echo "ready $n"; done
