# A whole evaluation on a lent GPU, one benchmark per call (the thirtieth session's lesson: eight workers compiling
# at once spent 196 s each before their first posterior; one process compiles in about 120 s cold):
#     bash results/gpu/device_evaluate.sh room      # then dark, in a second call on the warm machine
# Carry `.whl` (blackjax, arviz, xarray-einstats, h5netcdf, trimesh, platformdirs: see device_session30.sh) and
# `.devdata` with NAME-lo (the data set) and NAME-model (the fit, without starts/ and snapshots.npz). They are
# copied to /work/data/NAME-lo and /work/data/models/NAME-white, the paths of the machine that made them, because a
# run folder refuses posteriors of a data set or model in another folder (evaluate/jobs.py check_run). Returns the
# tables and the posterior cache as .txz parts: `cat eval-NAME.txz.* | tar xJf - -C /work/out` here, then
#     mitsuba-p3 evaluate data/NAME-lo --model data/models/NAME-white --out out/eval-NAME-gpu --likelihoods p3 \
#         --renderer jax --particles 64
# in /work resumes from the cache (a cut-short run samples the rest, on the CPU) and writes the tables again.
name=${1:?benchmark name, e.g. room}
export PYTHONUNBUFFERED=1
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD JAX_COMPILATION_CACHE_DIR=/tmp/jax-cache
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader | tee $OUT/gpu.txt
mkdir -p /work/data/models /work/out && cp -r .devdata/$name-lo /work/data/$name-lo && cp -r .devdata/$name-model /work/data/models/$name-white || exit 1
cd /work
start=$(date +%s)
timeout ${LIMIT:-540} python3 -m mitsuba_p3.cli evaluate data/$name-lo --model data/models/$name-white --out out/eval-$name-gpu \
  --likelihoods p3 --renderer jax --particles 64 --jobs ${JOBS:-1} > /tmp/eval-$name.log 2>&1
echo "$name rc $? after $(( $(date +%s) - start )) s" | tee -a /tmp/eval-$name.log
tr '\r' '\n' < /tmp/eval-$name.log | grep -v Warning | tail -30
cp /tmp/eval-$name.log out/eval-$name-gpu/ ; tar cJf /tmp/eval-$name.txz -C /work/out eval-$name-gpu && split -b 15M /tmp/eval-$name.txz $OUT/eval-$name.txz.
