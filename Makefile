# pusher-rl: `make demo` and `make test` do all the set-up on a fresh machine.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip --disable-pip-version-check -q
STAMP  := $(VENV)/.setup-done
ROS_PACKAGES := $(sort $(dir $(wildcard ros_ws/src/*/package.xml)))
ROS_FILES := $(wildcard ros_ws/src/*/package.xml ros_ws/src/*/setup.py ros_ws/src/*/setup.cfg)

.PHONY: setup demo push-demo test test-fast bag bench hil-demo hil-online clean help

help:
	@echo "make demo      set up .venv, then train BC and AWAC over ROS on bags/mix.db3 and print the comparison"
	@echo "make test      set up .venv, then run the whole test suite (slow end-to-end cases included)"
	@echo "make test-fast the suite without the slow end-to-end cases"
	@echo "make bag       regenerate bags/mix.db3 (bit-reproducible)"
	@echo "make bench     full benchmark against the reference implementations -> bench/results.json, then bench/RESULTS.md"
	@echo "make hil-demo  the corrections loop: serve, correct, record, retrain, reload"
	@echo "make hil-online the HIL-SERL stage: the online learner fine-tunes the prior while the policy node acts"
	@echo "make push-demo the push task end to end: expert, mixed log, BC and AWAC, a success classifier, online stage on it"

# The C++ step replayer of the speed layer (offline_rl_core/fast/csrc) compiles once into torch's extension cache;
# later runs only check it (about a second). Without a compiler the Python step runs.
setup: $(STAMP)
	@$(PY) -m offline_rl_core.fast.graph_runner || echo "(recorded training steps replay in Python)"

# Re-runs only when the project's packaging changes; torch goes in first so that
# nothing else can make pip pick a newer (CUDA) torch.
$(STAMP): pyproject.toml $(ROS_FILES) ros_ws/tools/ros_install.py
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PIP) install torch==2.13.0
	$(PIP) install -e '.[ros,dev,onnx]'
	@# Ray (the sweep's cluster engine) only where pip resolves it beside this torch; without it the
	@# sweep runs on local worker processes and the Ray tests skip
	@dry=$$($(PY) -m pip --disable-pip-version-check install --dry-run 'torch==2.13.0' -e '.[ray]' 2>&1) \
	  && ! printf '%s\n' "$$dry" | grep -q '^Would install.* torch-[0-9]' \
	  && $(PIP) install 'torch==2.13.0' -e '.[ray]' \
	  || echo "setup: Ray not installed (pip could not install it beside torch 2.13.0); offline-rl sweep --engine ray is unavailable"
	@# the live view's Foxglove WebSocket server (the viz extra), likewise only beside this torch
	@dry=$$($(PY) -m pip --disable-pip-version-check install --dry-run 'torch==2.13.0' -e '.[viz]' 2>&1) \
	  && ! printf '%s\n' "$$dry" | grep -q '^Would install.* torch-[0-9]' \
	  && $(PIP) install 'torch==2.13.0' -e '.[viz]' \
	  || echo "setup: foxglove-sdk not installed (pip could not install it beside torch 2.13.0); ros2 run viz live_view is unavailable"
	$(PY) ros_ws/tools/ros_install.py --venv $(VENV) $(ROS_PACKAGES)
	@touch $(STAMP)

demo: setup
	$(PY) -m offline_rl_core.pipelines.demo --out runs/demo

test: setup
	$(PY) -m pytest -q

test-fast: setup
	$(PY) -m pytest -q -m "not slow"

bag: setup
	$(VENV)/bin/offline-rl collect --episodes 200 --expert-frac 0.3 --seed 0 --out bags/mix.db3

bench: setup
	$(PIP) install -e '.[bench]'
	$(VENV)/bin/offline-rl bench --json bench/results.json
	$(PY) bench/results_page.py

hil-demo: setup
	$(VENV)/bin/offline-rl hil --out runs/hil

hil-online: setup
	$(VENV)/bin/offline-rl hil --online --out runs/hil-online

# pusher_push end to end at small budgets (PUSH_STEPS, PUSH_ENV_STEPS): its scripted expert, a mixed log of
# 200 episodes (30 % expert), BC and AWAC on it, a success classifier from 20 successes and 20 failures
# (labelled by the simulator, as a person would label them), and the online stage from the AWAC prior
# with the classifier's reward and episode end
PUSH := runs/push-demo
PUSH_STEPS ?= 4000
PUSH_ENV_STEPS ?= 3000
push-demo: setup
	mkdir -p $(PUSH)
	$(VENV)/bin/offline-rl eval --task pusher_push --expert --episodes 20
	$(VENV)/bin/offline-rl collect --task pusher_push --episodes 200 --expert-frac 0.3 --seed 0 --out $(PUSH)/push.db3
	$(VENV)/bin/offline-rl train --bag $(PUSH)/push.db3 --algo bc --steps $(PUSH_STEPS) --eval-episodes 20 --out $(PUSH)/bc
	$(VENV)/bin/offline-rl train --bag $(PUSH)/push.db3 --algo awac --steps $(PUSH_STEPS) --eval-episodes 20 --out $(PUSH)/awac
	$(VENV)/bin/offline-rl classifier train --bag $(PUSH)/push.db3 --labels simulator --successes 20 --failures 20 --head 16 \
		--out $(PUSH)/classifier.pt
	$(VENV)/bin/offline-rl hil --online --in-process --task pusher_push --bag $(PUSH)/push.db3 \
		--prior $(PUSH)/awac/policy.pt --success $(PUSH)/classifier.pt --end-on-success \
		--env-steps $(PUSH_ENV_STEPS) --eval-every 1500 --publish-every 50 --eval-episodes 20 --out $(PUSH)/online

clean:
	rm -rf runs build ros_ws/build ros_ws/install ros_ws/log
