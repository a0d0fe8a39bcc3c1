# toppledb: two commands on a fresh machine, `make dataset` and `make test`.
# Both depend on .venv, which this Makefile creates and fills by itself.

PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
ARGS   ?=
DATASET ?= data/dataset

.PHONY: venv dataset test bench bench-service corpus serve logs heldout clean

venv: $(VENV)/.installed

# constraints.txt pins every distribution to the versions last tested (see its header); build-constraints.txt
# pins pip and the build backend that installs toppledb itself.
$(VENV)/.installed: pyproject.toml constraints.txt build-constraints.txt
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "need $(PYTHON) on PATH (or make PYTHON=python3)"; exit 1; }
	test -d $(VENV) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet -c build-constraints.txt --upgrade pip
	$(PY) -m pip install --quiet -c constraints.txt --build-constraint build-constraints.txt -e ".[all,dev]" \
		--config-settings editable_mode=compat
	touch $@

dataset: venv
	$(PY) -m pipeline dataset $(ARGS)

test: venv
	$(PY) -m pytest -q $(ARGS)

bench: venv
	$(PY) -m pipeline bench $(ARGS)

# Starts the service on data/dataset (else a small dataset it builds), loads it over TCP with a
# light asyncio HTTP/1.1 client (service/bench.py), prints one JSON line; about 30 s.
bench-service: venv
	$(PY) -m service.bench $(ARGS)

corpus: venv
	$(PY) -m pipeline corpus $(ARGS)

serve: venv
	$(PY) -m pipeline serve --dataset $(DATASET) $(ARGS)

# Push-outcome logs played in pybullet (docs/VALIDATION.md): corpus objects to calibrate on,
# objects outside the corpus to report on. About 5,000 pushes each; resumable. The player's
# noise and push sampling are the thesis's, so the simulated world stays put when the model is tuned.
# The replays play the same pushes again with other noise draws, 40 repeats each: the reports'
# physics_replay reference (what any predictor can reach). About 12 minutes each on 2 cores.
# corpus_all, every corpus object's drawn pushes, is what the default's map of P(topple) is
# fitted on (docs/MODEL.md C.7; about 13 minutes on 2 cores).
logs: venv
	$(PY) -m pipeline play --config thesis --objects corpus --count 42 --out data/logs/corpus $(ARGS)
	$(PY) -m pipeline play --config thesis --objects heldout --count 50 --out data/logs/heldout $(ARGS)
	$(PY) -m pipeline play --config thesis --objects corpus --out data/logs/corpus_all $(ARGS)
	$(PY) -m pipeline play --config thesis --objects corpus --actions 8 --seed 1 --out data/logs/corpus_s1 $(ARGS)
	@# heldout_b to _k: held-out objects 101-600, fifty to a log, each judged by one candidate at most.
	skip=100; for log in b c d e f g h i j k; do \
		$(PY) -m pipeline play --config thesis --objects heldout --count 50 --skip $$skip --out data/logs/heldout_$$log $(ARGS) || exit 1; \
		skip=$$((skip + 50)); \
	done
	$(PY) -m pipeline play --config thesis --objects corpus --count 42 --repeats 40 --noise-draws 1 --out data/logs/corpus_replay $(ARGS)
	$(PY) -m pipeline play --config thesis --objects heldout --count 50 --repeats 40 --noise-draws 1 --out data/logs/heldout_replay $(ARGS)

# The six held-out datasets the policy runs are judged on (docs/VALIDATION.md): every object of the
# held-out order outside the corpus, in sets of 100-200, each with its corpus list. Every set is checked
# against the current model: shards whose inputs are unchanged are reused (a few seconds a set), so a killed
# run resumes; a set built with another model stops it with the difference, and `make heldout ARGS=--force`
# rebuilds them all (each old set stays until its new one is complete). About 16 minutes on 2 cores.
HELDOUT_SETS := "a 100 0 first_100" "b 100 100 101_200" "c 200 200 201_400" "d 150 450 451_600" \
	"e 150 600 601_750" "f 150 750 751_900"
heldout: venv
	@for set in $(HELDOUT_SETS); do \
		set -- $$set; \
		test -f data/heldout_$$4.csv || $(PY) -m pipeline play --objects heldout --count $$2 --skip $$3 --list data/heldout_$$4.csv || exit 1; \
		$(PY) -m pipeline dataset --corpus data/heldout_$$4.csv --out data/heldout_sa_$$1 --workers 2 $(ARGS) || exit 1; \
	done

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
