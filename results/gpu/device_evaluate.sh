# A whole evaluation on a lent GPU, one benchmark per call (the thirtieth session's lesson: eight workers compiling
# at once spent 196 s each before their first posterior; one process compiles in about 120 s cold):
#     bash results/gpu/device_evaluate.sh room      # then dark, in a second call on the warm machine
# Carry `.whl` (blackjax, arviz, xarray-einstats, h5netcdf, trimesh, platformdirs: see device_session30.sh) and
# `.devdata` with NAME-lo (the data set) and NAME-model (the fit, without starts/ and snapshots.npz). Returns the
# tables and the posterior cache as .txz parts: `cat eval-NAME.txz.* | tar xJf -`, then the same evaluate command
# on any machine (with --renderer jax --particles 64) resumes from the cache and writes the tables again.
name=${1:?benchmark name, e.g. room}
export PYTHONUNBUFFERED=1
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD JAX_COMPILATION_CACHE_DIR=/tmp/jax-cache
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader | tee $OUT/gpu.txt
start=$(date +%s)
timeout ${LIMIT:-540} python3 -m mitsuba_p3.cli evaluate .devdata/$name-lo --model .devdata/$name-model --out /tmp/eval-$name \
  --likelihoods p3 --renderer jax --particles 64 --jobs ${JOBS:-1} > /tmp/eval-$name.log 2>&1
echo "$name rc $? after $(( $(date +%s) - start )) s" | tee -a /tmp/eval-$name.log
tr '\r' '\n' < /tmp/eval-$name.log | grep -v Warning | tail -30
tar cJf /tmp/eval-$name.txz -C /tmp eval-$name eval-$name.log && split -b 15M /tmp/eval-$name.txz $OUT/eval-$name.txz.
