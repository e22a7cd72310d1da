# lungdeform: two commands for a fresh machine.
#   make demo   builds and plays the embedded default lungs into ./demo-out
#   make test   runs the whole test suite (real-data tests need LUNGDEFORM_DATA)
# Each target installs what it needs into .venv/ (pinned in requirements.lock).

PYTHON ?= $(shell command -v python3.11 || command -v python3.12 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
BLENDER_VENV := .venv-blender
BLENDER_STAMP := $(BLENDER_VENV)/.installed
DEMO_OUT ?= demo-out

.PHONY: demo test install clean fuzz

install: $(STAMP)

$(STAMP): pyproject.toml requirements.lock
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "lungdeform needs Python >= 3.11")'
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -r requirements.lock
	$(BIN)/python -m pip install -q --no-deps --no-build-isolation -e .
	@touch $(STAMP)

demo: $(STAMP)
	$(BIN)/lungdeform demo --out $(DEMO_OUT)

test: $(STAMP) viewer-deps $(VIEWER_BUNDLE) dicom3tools blender $(BLENDER_STAMP)
	$(BIN)/python -m pytest $(PYTEST_ARGS)

# --- fuzzing: every file reader under atheris (coverage guided; a seeded random-mutation fuzzer when
# atheris is missing), FUZZ_RUNS executions or FUZZ_SECONDS seconds per reader, whichever comes
# first; executions and unique crashes per reader, with a reproducer each, in fuzz-out/fuzz.json.
FUZZ_RUNS ?= 1000000
FUZZ_SECONDS ?= 60
FUZZ_OUT ?= fuzz-out
FUZZ_STAMP := $(VENV)/.fuzz-installed

$(FUZZ_STAMP): $(STAMP)
	$(BIN)/python -m pip install -q "atheris==3.0.0" || echo "atheris did not install: fuzzing with the random-mutation fallback"
	@touch $(FUZZ_STAMP)

fuzz: $(FUZZ_STAMP)
	$(BIN)/python tests/fuzz/run.py --runs $(FUZZ_RUNS) --seconds $(FUZZ_SECONDS) --out $(FUZZ_OUT) $(FUZZ_READERS)

# --- browser viewer (issue 5), for `make test`: the viewer's node packages (npm ci, once: stamp),
# Debian's Chromium for the Playwright test (installed as root when /usr/bin/chromium is missing),
# and the viewer bundle shipped in the package (rebuilt when its sources are newer). Without npm
# or root the viewer's node and browser tests skip, naming what is missing.
VIEWER_STAMP := viewer/node_modules/.installed
VIEWER_BUNDLE := src/lungdeform/data/viewer/index.html
VIEWER_SRC := $(wildcard viewer/src/*.ts viewer/src/*.css) viewer/index.html viewer/vite.config.ts viewer/package-lock.json

.PHONY: viewer-deps chromium dicom3tools
viewer-deps: $(VIEWER_STAMP) chromium

$(VIEWER_STAMP): viewer/package.json viewer/package-lock.json
	@if command -v npm >/dev/null; then cd viewer && npm ci --no-audit --no-fund && touch node_modules/.installed; \
	else echo "npm not found: the viewer's node tests and the browser test will skip"; fi

chromium:
	@if [ ! -x /usr/bin/chromium ]; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends chromium; \
	  else echo "/usr/bin/chromium missing and not root: the browser test will skip"; fi; \
	fi

# Debian's dicom3tools for dciodvfy, which checks every DICOM file lungdeform writes against its IOD
# (tests/io/dicom/test_conformance.py; installed as root when missing, else those tests skip).
dicom3tools:
	@if [ ! -x /usr/bin/dciodvfy ]; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends dicom3tools; \
	  else echo "/usr/bin/dciodvfy missing and not root: the DICOM conformance tests will skip"; fi; \
	fi

# Blender for the importer tests (tests/playback/test_export.py, test_usd.py): Debian's blender (3.4.1,
# glTF importer; built without USD) with python3-numpy, installed as root when /usr/bin/blender is
# missing; and Blender as a Python module (bpy from PyPI, with its USD importer) in .venv-blender/
# (pinned in requirements-blender.lock). Without them those tests skip, naming what is missing.
.PHONY: blender
blender:
	@if [ ! -x /usr/bin/blender ] || { command -v dpkg >/dev/null && ! dpkg -s python3-numpy >/dev/null 2>&1; }; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends blender python3-numpy; \
	  else echo "/usr/bin/blender missing and not root: the Blender glTF test will skip"; fi; \
	fi

$(BLENDER_STAMP): requirements-blender.lock
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info[:2] == (3, 11) else 1)' && \
	  $(PYTHON) -m venv $(BLENDER_VENV) && $(BLENDER_VENV)/bin/python -m pip install -q -r requirements-blender.lock && \
	  touch $(BLENDER_STAMP) || echo "bpy (Blender as a module) needs Python 3.11: the Blender USD tests will skip"

$(VIEWER_BUNDLE): $(VIEWER_SRC) | $(VIEWER_STAMP)
	@if [ -d viewer/node_modules ]; then cd viewer && npm run build; \
	else echo "viewer/node_modules missing: keeping the committed viewer bundle"; fi

clean:
	rm -rf $(VENV) $(BLENDER_VENV) $(DEMO_OUT) $(FUZZ_OUT) build src/*.egg-info .pytest_cache
