# Where a P3 posterior's seconds go on a lent GPU (issue 44): the JAX tracer end to end (no Mitsuba),
# the default SMC and the gradient move at lambda = 1, each profiled on its last image.
export PYTHONUNBUFFERED=1
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv | tee $OUT/gpu.txt
python3 -c "import jax; print(jax.__version__, jax.devices())" 2>&1 | tail -1 | tee $OUT/jax.txt
for run in "default" "final3 --set smc.final_gradient_steps=3"; do
  set -- $run
  name=$1; shift
  echo "== $name"
  timeout 200 python3 scripts/bench_posterior.py .devdata/model .devdata/images/0[0-5].png --renderer jax --particles 64 \
    --truth .devdata/images/truth.json --profile $OUT/profile_$name.txt "$@" > $OUT/bench_posterior_$name.json 2> $OUT/$name.err
  grep median $OUT/bench_posterior_$name.json | head -2; tail -2 $OUT/$name.err
done
