// The backlight Python module (pybind11): load a scene, read and write its parameters through
// zero-copy NumPy views, render, and run adjoint passes. python/backlight/__init__.py re-exports
// it; python/backlight/torch.py wraps render + backward as a torch.autograd.Function.
//
// Conventions: images are NumPy float32 arrays of shape (height, width, 3), row 0 at the top,
// the layout of the film and of EXR files. Errors a user can cause (bad files, unknown names,
// arrays of the wrong shape, dtype or layout, NaN) raise backlight.Error (a ValueError) with the
// CLI's one-line message; renders release the GIL and run on the TBB pool.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstring>
#include <exception>
#include <limits>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "engine/core/errors.h"
#include "engine/core/limits.h"
#include "engine/integrators/gradient.h"
#include "engine/integrators/render.h"
#include "engine/scene/scene_load.h"
#include "tbb/global_control.h"

namespace py = pybind11;
using namespace bl;

namespace {

// A loaded scene. Parameter views point into its ParamStore, whose buffers are never resized
// after loading, and keep this object alive through their base.
struct PyScene {
  std::unique_ptr<Scene> scene;
  std::string path;
  // One pass at a time: a pass resizes the camera's film and rebuilds sampling data, so two
  // Python threads passing the same scene would corrupt each other's pass (they crashed).
  std::mutex busy;
};

// Holds the scene's `busy` lock for one pass; waits for it without the GIL (the thread holding
// it needs the GIL to finish).
std::unique_lock<std::mutex> lock_for_pass(PyScene& s) {
  std::unique_lock<std::mutex> lock(s.busy, std::defer_lock);
  if (!lock.try_lock()) {
    py::gil_scoped_release release;
    lock.lock();
  }
  return lock;
}

std::vector<py::ssize_t> shape_of(const Param& p) { return {p.shape.begin(), p.shape.end()}; }

std::vector<py::ssize_t> strides_of(const std::vector<py::ssize_t>& shape) {
  std::vector<py::ssize_t> strides(shape.size());
  py::ssize_t step = py::ssize_t(sizeof(float));
  for (size_t i = shape.size(); i-- > 0;) {
    strides[i] = step;
    step *= shape[i];
  }
  return strides;
}

// A NumPy array that owns `values` (no copy).
py::array_t<float> owning_array(std::vector<float>&& values, std::vector<py::ssize_t> shape) {
  auto* heap = new std::vector<float>(std::move(values));
  py::capsule owner(heap, [](void* p) { delete static_cast<std::vector<float>*>(p); });
  auto strides = strides_of(shape);
  return py::array_t<float>(shape, strides, heap->data(), owner);
}

py::array_t<float> image_array(Image&& image) {
  return owning_array(std::move(image.data), {image.height, image.width, image.channels});
}

// `text` as a str, bytes that are not UTF-8 shown as \xNN (file names need not be UTF-8).
py::str utf8_or_escaped(const std::string& text) {
  PyObject* s = PyUnicode_DecodeUTF8(text.data(), Py_ssize_t(text.size()), "backslashreplace");
  if (!s) throw py::error_already_set();
  return py::reinterpret_steal<py::str>(s);
}

// Checks that `obj` is a C-contiguous float32 array of exactly `shape` with finite values and
// returns it; `what` names it in the error.
py::array_t<float> checked_array(const py::handle& obj, const std::vector<py::ssize_t>& shape,
                                 const std::string& what) {
  if (!py::isinstance<py::array>(obj))
    throw InputError(what + ": expected a NumPy array, got " + std::string(py::str(obj.get_type().attr("__name__"))));
  py::array a = py::reinterpret_borrow<py::array>(obj);
  if (!a.dtype().is(py::dtype::of<float>()))
    throw InputError(what + ": expected dtype float32, got " + std::string(py::str(a.dtype())) +
                     " (convert with .astype(numpy.float32))");
  std::string want = "(", got = "(";
  for (size_t i = 0; i < shape.size(); ++i) want += (i ? ", " : "") + std::to_string(shape[i]);
  for (py::ssize_t i = 0; i < a.ndim(); ++i) got += (i ? ", " : "") + std::to_string(a.shape(i));
  want += ")", got += ")";
  bool same = size_t(a.ndim()) == shape.size();
  for (size_t i = 0; same && i < shape.size(); ++i) same = a.shape(py::ssize_t(i)) == shape[i];
  if (!same) throw InputError(what + ": expected shape " + want + ", got " + got);
  if (!(a.flags() & py::array::c_style))
    throw InputError(what + ": the array is not C-contiguous (use numpy.ascontiguousarray)");
  auto f = py::reinterpret_borrow<py::array_t<float>>(a);
  const float* data = f.data();
  for (py::ssize_t i = 0; i < f.size(); ++i)
    if (!std::isfinite(data[i])) throw InputError(what + ": element " + std::to_string(i) + " is NaN or infinite");
  return f;
}

// Parameters may have been written through their views since the last pass: check them (finite,
// in range) and rebuild what depends on them (environment sampling, medium majorants).
void refresh(PyScene& s) {
  for (const Param& p : s.scene->params.all()) validate_param(p, s.path);
  s.scene->prepare_sampling();
}

// Keyword arguments are converted here rather than by pybind11's casters, whose TypeError
// ("incompatible function arguments") named neither the argument nor the problem.
std::string type_name(const py::handle& v) { return py::str(v.get_type().attr("__name__")); }
std::string repr_of(const py::handle& v) { return py::repr(v); }

py::int_ index_arg(const py::object& v, const std::string& name) {
  if (py::isinstance<py::bool_>(v) || !PyIndex_Check(v.ptr()))
    throw InputError(name + ": expected an integer, got " + type_name(v) + " " + repr_of(v));
  PyObject* i = PyNumber_Index(v.ptr());
  if (!i) {  // an object whose __index__ fails (torch.tensor(2.5)): its message, with our name
    const py::error_already_set e;
    throw InputError(name + ": expected an integer, got " + type_name(v) + " " + repr_of(v) + " (" + e.what() + ")");
  }
  return py::reinterpret_steal<py::int_>(i);
}

std::optional<int> int_arg(const py::object& v, const std::string& name, long long lo, long long hi) {
  if (v.is_none()) return std::nullopt;
  const py::int_ i = index_arg(v, name);
  int overflow = 0;
  const long long x = PyLong_AsLongLongAndOverflow(i.ptr(), &overflow);
  if (overflow || x < lo || x > hi)
    throw InputError(name + ": " + repr_of(v) + " is out of range (" + std::to_string(lo) + ".." + std::to_string(hi) +
                     ")");
  return int(x);
}

std::optional<uint64_t> seed_arg(const py::object& v, const std::string& name) {
  if (v.is_none()) return std::nullopt;
  const py::int_ i = index_arg(v, name);
  const unsigned long long x = PyLong_AsUnsignedLongLong(i.ptr());
  if (PyErr_Occurred()) {
    PyErr_Clear();
    throw InputError(name + ": " + repr_of(v) + " is out of range (an integer in 0..2^64 - 1)");
  }
  return uint64_t(x);
}

// The same for arguments that have a default and no "not given" (None there is a mistake: it was
// dereferenced as an empty optional, and resolution=(None, None) rendered at a size from memory).
int required_int_arg(const py::object& v, const std::string& name, long long lo, long long hi) {
  if (v.is_none()) throw InputError(name + ": expected an integer, got NoneType None");
  return *int_arg(v, name, lo, hi);
}
uint64_t required_seed_arg(const py::object& v, const std::string& name) {
  if (v.is_none()) throw InputError(name + ": expected an integer, got NoneType None");
  return *seed_arg(v, name);
}

std::optional<std::pair<int, int>> resolution_arg(const py::object& v) {
  if (v.is_none()) return std::nullopt;
  if (!(py::isinstance<py::tuple>(v) || py::isinstance<py::list>(v)) || py::len(v) != 2)
    throw InputError("resolution: expected (width, height), got " + repr_of(v));
  const py::sequence wh = py::reinterpret_borrow<py::sequence>(v);
  const py::object w = wh[0], h = wh[1];
  return std::pair{required_int_arg(w, "resolution: width", 1, 16384),
                   required_int_arg(h, "resolution: height", 1, 16384)};
}

// The scene argument: something else (None, a file name) gave pybind11's TypeError of five lines
// (the signature and the call) instead of one naming the argument.
PyScene& scene_arg(const py::object& v) {
  if (!py::isinstance<PyScene>(v))
    throw InputError("scene: expected a backlight.Scene (backlight.load), got " + type_name(v));
  return v.cast<PyScene&>();
}

std::string str_arg(const py::object& v, const std::string& name) {
  if (!py::isinstance<py::str>(v)) throw InputError(name + ": expected a str, got " + type_name(v) + " " + repr_of(v));
  return v.cast<std::string>();
}

// params=: a list (or tuple) of parameter names, each known to the scene.
std::optional<std::vector<std::string>> names_arg(const py::object& v, const ParamStore& store) {
  if (v.is_none()) return std::nullopt;
  if (py::isinstance<py::str>(v))
    throw InputError("params: expected a list of parameter names, got the str " + repr_of(v) + " (params=[" +
                     repr_of(v) + "])");
  if (!(py::isinstance<py::list>(v) || py::isinstance<py::tuple>(v)))
    throw InputError("params: expected a list of parameter names, got " + type_name(v));
  std::vector<std::string> names;
  for (const py::handle& item : v) {
    const std::string name = str_arg(py::reinterpret_borrow<py::object>(item), "params");
    if (store.find(name) < 0) throw InputError("params: unknown parameter '" + name + "' (see scene.params)");
    names.push_back(name);
  }
  return names;
}

struct PassArgs {
  std::optional<int> spp;
  std::optional<uint64_t> seed;
  int camera = 0;
  std::optional<std::pair<int, int>> resolution;  // (width, height)
};

PassArgs pass_args(const py::object& spp, const py::object& seed, const py::object& camera,
                   const py::object& resolution) {
  PassArgs a;
  a.spp = int_arg(spp, "spp", 1, int(limits::kSpp));
  a.seed = seed_arg(seed, "seed");
  a.camera = int_arg(camera, "camera", INT32_MIN, INT32_MAX).value_or(0);  // range: CameraScope
  a.resolution = resolution_arg(resolution);
  return a;
}

// Applies a pass's camera and resolution; restores the camera's film size when destroyed.
class CameraScope {
 public:
  CameraScope(Scene& scene, const PassArgs& a) {
    if (a.camera < 0 || size_t(a.camera) >= scene.cameras.size())
      throw InputError("camera " + std::to_string(a.camera) + ": the scene has " +
                       std::to_string(scene.cameras.size()) + " camera(s)");
    camera_ = &scene.cameras[size_t(a.camera)];
    saved_ = {camera_->width, camera_->height};
    if (a.resolution) {
      const auto [w, h] = *a.resolution;
      if (w < 1 || h < 1 || w > 16384 || h > 16384)
        throw InputError("resolution (" + std::to_string(w) + ", " + std::to_string(h) +
                         "): expected (width, height), each in 1..16384");
      camera_->width = w, camera_->height = h;
      camera_->update();
    }
  }
  ~CameraScope() {
    camera_->width = saved_.first, camera_->height = saved_.second;
    camera_->update();
  }
  CameraScope(const CameraScope&) = delete;
  CameraScope& operator=(const CameraScope&) = delete;
  const Camera& camera() const { return *camera_; }

 private:
  Camera* camera_ = nullptr;
  std::pair<int, int> saved_;
};

PassOptions pass_options(const Scene& scene, const PassArgs& a) {
  PassOptions o;
  o.camera = a.camera;
  o.spp = a.spp.value_or(scene.settings.spp);
  if (o.spp < 1) throw InputError("spp must be ≥ 1");
  limits::require_at_most("spp", "sample count", uint64_t(o.spp), limits::kSpp);
  o.seed = a.seed.value_or(scene.settings.seed);
  o.progress = false;
  return o;
}

std::unique_ptr<PyScene> load(const std::string& path, const std::optional<py::dict>& set, std::optional<int> max_depth,
                              std::optional<int> rr_depth);

// load's arguments: a path (str or os.PathLike), {name: value} overrides, depths.
std::unique_ptr<PyScene> load_py(const py::object& path, const py::object& set, const py::object& max_depth,
                                 const py::object& rr_depth) {
  if (!py::isinstance<py::str>(path) && !py::isinstance<py::bytes>(path) && !py::hasattr(path, "__fspath__"))
    throw InputError("path: expected a file name (str, bytes or os.PathLike), got " + type_name(path));
  // As bytes: a str with surrogate escapes (a non-UTF-8 name from os.listdir) cannot be cast to
  // UTF-8; os.fsencode gives the name the file system has.
  const py::object name = py::module_::import("os").attr("fsencode")(path);
  std::optional<py::dict> overrides;
  if (!set.is_none()) {
    if (!py::isinstance<py::dict>(set))
      throw InputError("set: expected a dict {name: value}, got " + type_name(set) + " " + repr_of(set));
    overrides = py::reinterpret_borrow<py::dict>(set);
  }
  return load(std::string(py::reinterpret_borrow<py::bytes>(name)), overrides,
              int_arg(max_depth, "max_depth", -1, 1 << 20), int_arg(rr_depth, "rr_depth", 0, 1 << 20));
}

std::unique_ptr<PyScene> load(const std::string& path, const std::optional<py::dict>& set, std::optional<int> max_depth,
                              std::optional<int> rr_depth) {
  auto s = std::make_unique<PyScene>();
  s->path = path;
  s->scene = load_scene(path);
  if (max_depth) {
    if (*max_depth == 0 || *max_depth < -1) throw InputError("max_depth must be ≥ 1, or -1 for unlimited");
    s->scene->settings.max_depth = *max_depth;
  }
  if (rr_depth) {
    if (*rr_depth < 0) throw InputError("rr_depth must be ≥ 0");
    s->scene->settings.rr_depth = *rr_depth;
  }
  if (set) {
    for (const auto& [key, value] : *set) {
      const std::string name = py::str(key);
      if (s->scene->params.find(name) < 0) throw InputError("set: unknown parameter '" + name + "' (see scene.params)");
      // A file name (str), or numbers: a number, a (nested) sequence or an array, taken in C order.
      if (py::isinstance<py::str>(value)) {
        const std::string file = py::str(value);
        if (file.empty()) throw InputError("set: '" + name + "': an empty file name");
        try {
          apply_override(*s->scene, name + "=" + file);
        } catch (const InputError& e) {  // its messages speak of the CLI's --set
          std::string m = e.what();
          for (const char* prefix : {"--set: ", "--set "})
            if (m.rfind(prefix, 0) == 0) m = "set: " + m.substr(std::strlen(prefix));
          throw InputError(m);
        }
        continue;
      }
      // NumPy refuses a tensor that requires grad, which the message below called "got Tensor".
      if (py::hasattr(value, "requires_grad") && py::hasattr(value, "detach") &&
          PyObject_IsTrue(value.attr("requires_grad").ptr()) == 1)
        throw InputError("set: '" + name +
                         "': a tensor that requires grad (set= copies values once and gives no gradient): pass "
                         "tensor.detach(), or render through backlight.torch.render(scene, {name: tensor}) for its "
                         "gradient");
      if (value.is_none())  // forcecast makes it a NaN
        throw InputError("set: '" + name +
                         "': expected a number, numbers (a list or an array) or an image file name, got None");
      auto numbers = py::array_t<float, py::array::c_style | py::array::forcecast>::ensure(value);
      if (py::isinstance<py::bool_>(value) || !numbers) {
        PyErr_Clear();
        throw InputError("set: '" + name +
                         "': expected a number, numbers (a list or an array) or an image file name, got " +
                         type_name(value));
      }
      // A flat sequence is taken in C order; an array of more dimensions must have the parameter's
      // shape (dimensions of size 1 aside): a (3, H, W) texture from PyTorch scrambled its channels.
      if (numbers.ndim() >= 2) {
        const Param& p = s->scene->params[s->scene->params.find(name)];
        std::vector<int> want, got;
        for (int d : p.shape)
          if (d != 1) want.push_back(d);
        for (py::ssize_t d = 0; d < numbers.ndim(); ++d)
          if (numbers.shape(d) != 1) got.push_back(int(numbers.shape(d)));
        if (want != got) {
          std::string w = "(", g = "(";
          for (size_t i = 0; i < p.shape.size(); ++i) w += (i ? ", " : "") + std::to_string(p.shape[i]);
          for (py::ssize_t d = 0; d < numbers.ndim(); ++d) g += (d ? ", " : "") + std::to_string(numbers.shape(d));
          throw InputError("set: '" + name + "': expected shape " + w + ") or a flat sequence, got " + g + ")");
        }
      }
      set_param_values(*s->scene, name, std::vector<float>(numbers.data(), numbers.data() + numbers.size()), "set");
    }
    s->scene->prepare_sampling();
  }
  return s;
}

// Raises SystemExit in a thread whose pass the interpreter's exit stopped (or refused). As an
// Error its traceback was printed by threading's excepthook while the interpreter finalized, cut
// off mid-line ("Exception in thread Thread-1 (<lambda>):\nTraceback ...", 5 runs in 5 with torch
// imported); threading and _thread end a thread on SystemExit without a word.
[[noreturn]] void exit_thread(const char* why) {
  PyErr_SetString(PyExc_SystemExit, why);
  throw py::error_already_set();
}

// Passes running now, so that interpreter exit can stop them first (stop_passes_at_exit).
struct RunningPasses {
  std::mutex m;
  std::condition_variable changed;
  std::vector<std::atomic<bool>*> cancels;
  bool exiting = false;
};
RunningPasses& running_passes() {
  static auto* r = new RunningPasses;  // never destroyed: daemon threads may still use it at exit
  return *r;
}

bool python_finalizing() {
#if PY_VERSION_HEX >= 0x030D0000
  return Py_IsFinalizing() != 0;
#else
  return _Py_IsFinalizing() != 0;
#endif
}

// backlight.set_threads: TBB's max_allowed_parallelism, as the CLI's --threads sets it. It is
// process-wide (every pass of every thread), like torch.set_num_threads, and it is what the
// gradient's per-thread buffers are sized by (GradientSink), so a gradient pass on n threads here
// sums as the CLI's on n. Changed only with the GIL held; put back at exit (stop_passes_at_exit),
// before TBB's own teardown.
std::unique_ptr<tbb::global_control>& thread_limit() {
  static auto* limit = new std::unique_ptr<tbb::global_control>;
  return *limit;
}
constexpr int kMaxThreads = int(limits::kThreads);  // the CLI's --threads limit

void set_threads(const py::object& threads) {
  if (threads.is_none()) {
    thread_limit().reset();
    return;
  }
  const int n = required_int_arg(threads, "threads", 1, kMaxThreads);
  thread_limit() = std::make_unique<tbb::global_control>(tbb::global_control::max_allowed_parallelism, size_t(n));
}

int get_threads() { return int(tbb::global_control::active_value(tbb::global_control::max_allowed_parallelism)); }

// Registered with Python's atexit (which runs before the interpreter starts to finalize): cancels
// the passes still running in other threads (a daemon thread's render) and waits, without the
// GIL, until they have stopped after their current tiles, so that none runs on while the process
// tears down; later passes refuse to start.
void stop_passes_at_exit() {
  RunningPasses& r = running_passes();
  {
    py::gil_scoped_release release;
    std::unique_lock<std::mutex> lock(r.m);
    r.exiting = true;
    for (std::atomic<bool>* c : r.cancels) *c = true;
    r.changed.wait_for(lock, std::chrono::seconds(30), [&] { return r.cancels.empty(); });
  }
  thread_limit().reset();
}

// Runs `pass(cancel)` (a render or gradient pass, `cancel` for its PassOptions) on a worker thread
// while this one, without the GIL, looks for signals every 50 ms: Ctrl-C raises
// KeyboardInterrupt once the pass has stopped after its current tiles. (Python handles signals
// between bytecodes of its main thread: a pass run on this thread kept Ctrl-C waiting to its end.)
// The GIL is released and taken back by hand, not by pybind11's scoped guards: once the
// interpreter finalizes (a daemon thread's pass at exit), taking the GIL ends the calling thread
// by pthread_exit, and in a guard's destructor that unwinding aborted the process
// (std::terminate). Whatever leaves this frame, the worker is stopped and joined first.
template <class Pass>
void interruptible(Pass&& pass) {
  std::atomic<bool> cancel{false};
  RunningPasses& passes = running_passes();
  {
    const std::lock_guard<std::mutex> lock(passes.m);
    if (passes.exiting) exit_thread("the interpreter is exiting: no new pass starts");
    passes.cancels.push_back(&cancel);
  }
  struct Unregister {
    RunningPasses& passes;
    std::atomic<bool>* cancel;
    ~Unregister() {
      const std::lock_guard<std::mutex> lock(passes.m);
      passes.cancels.erase(std::find(passes.cancels.begin(), passes.cancels.end(), cancel));
      passes.changed.notify_all();
    }
  } unregister{passes, &cancel};
  std::exception_ptr failure;
  std::mutex m;
  std::condition_variable finished;
  bool done = false, interrupted = false;
  PyThreadState* state = PyEval_SaveThread();
  std::thread worker;
  try {
    worker = std::thread([&] {
      try {
        pass(&cancel);
      } catch (...) {
        failure = std::current_exception();
      }
      const std::lock_guard<std::mutex> lock(m);
      done = true;
      finished.notify_one();
    });
  } catch (...) {
    PyEval_RestoreThread(state);
    throw;
  }
  struct Join {
    std::thread& worker;
    std::atomic<bool>& cancel;
    ~Join() {
      if (!worker.joinable()) return;
      cancel = true;
      worker.join();
    }
  } join{worker, cancel};
  std::unique_lock<std::mutex> lock(m);
  while (!finished.wait_for(lock, std::chrono::milliseconds(50), [&] { return done; })) {
    if (interrupted || cancel) continue;
    if (python_finalizing()) {
      cancel = true;
      continue;
    }
    lock.unlock();
    PyEval_RestoreThread(state);
    if (PyErr_CheckSignals() != 0) interrupted = true;  // the exception stays set for below
    state = PyEval_SaveThread();
    if (interrupted) cancel = true;
    lock.lock();
  }
  lock.unlock();
  worker.join();
  PyEval_RestoreThread(state);
  if (interrupted) throw py::error_already_set();
  if (failure) std::rethrow_exception(failure);
  // Stopped by stop_passes_at_exit (or by finalization): the result is partial.
  if (cancel) exit_thread("the pass was stopped: the interpreter is exiting");
}

py::array_t<float> render_py(PyScene& s, const PassArgs& a) {
  const auto lock = lock_for_pass(s);
  refresh(s);
  CameraScope scope(*s.scene, a);
  const PassOptions o = pass_options(*s.scene, a);
  Image image;
  interruptible([&](const std::atomic<bool>* cancel) {
    PassOptions with_cancel = o;
    with_cancel.cancel = cancel;
    image = render(*s.scene, with_cancel);
  });
  return image_array(std::move(image));
}

py::dict gradients_of(const Scene& scene) {
  py::dict out;
  for (const Param& p : scene.params.all())
    if (p.requires_grad) out[py::str(p.name)] = owning_array(std::vector<float>(p.grad), shape_of(p));
  return out;
}

void require(Scene& scene, const std::optional<std::vector<std::string>>& params) {
  const std::vector<std::string> names = params.value_or(std::vector<std::string>{});
  if (params && names.empty()) throw InputError("params: an empty list (omit it to differentiate every parameter)");
  scene.params.require_grad(names);
}

// The request of a gradient pass (backward, grad, check): `image` checked against the film and
// copied into `img`, the target of a loss when `loss` is given, else the adjoint image.
GradientRequest request_for(const Scene& scene, const Camera& cam, const py::handle& image, const char* what,
                            const std::string* loss, const std::string& method, const PassArgs& a,
                            std::optional<uint64_t> adjoint_seed, Image& img) {
  auto arr = checked_array(image, {cam.height, cam.width, 3}, what);
  img = Image(cam.width, cam.height, 3);
  std::copy(arr.data(), arr.data() + arr.size(), img.data.begin());
  GradientRequest rq;
  rq.method = parse_method(method);
  if (loss) {
    rq.loss = parse_loss(*loss);
    rq.target = &img;
  } else {
    rq.adjoint_image = &img;
  }
  rq.pass = pass_options(scene, a);
  rq.adjoint_seed = adjoint_seed.value_or(rq.pass.seed);
  return rq;
}

// The engine's messages name the CLI's flags ("--eps 1e-12: ... (use a larger --eps)", "--method
// taped ...: --adjoint-seed must equal --seed"); Python callers gave keyword arguments.
std::string keyword_names(std::string m) {
  static const std::pair<std::string, std::string> flags[] = {{"--adjoint-image", "d_image"},
                                                              {"--adjoint-seed", "adjoint_seed"},
                                                              {"--seeds", "seeds"},
                                                              {"--seed", "seed"},
                                                              {"--eps", "eps"},
                                                              {"--method", "method"},
                                                              {"--spp", "spp"},
                                                              {"--directions", "directions"},
                                                              {"--tolerance", "tolerance"},
                                                              {"--target", "target"}};
  for (const auto& [flag, keyword] : flags)
    for (size_t at = m.find(flag); at != std::string::npos; at = m.find(flag, at + keyword.size()))
      m.replace(at, flag.size(), keyword);
  return m;
}

template <class F>
auto with_keyword_names(F&& f) -> decltype(f()) {
  try {
    return f();
  } catch (const InputError& e) {
    throw InputError(keyword_names(e.what()));
  }
}

// backward and grad: the image argument (d_image, or the target when `loss` is given) checked
// against the film, the request built, and the pass run without the GIL.
GradientResult gradient_pass(PyScene& s, const py::handle& image, const char* what, const std::string* loss,
                             const std::string& method, const PassArgs& a, std::optional<uint64_t> adjoint_seed,
                             const std::optional<std::vector<std::string>>& params) {
  refresh(s);
  CameraScope scope(*s.scene, a);
  Image img;
  GradientRequest rq = request_for(*s.scene, scope.camera(), image, what, loss, method, a, adjoint_seed, img);
  require(*s.scene, params);
  GradientResult result;
  interruptible([&](const std::atomic<bool>* cancel) {
    rq.pass.cancel = cancel;
    result = with_keyword_names([&] { return compute_gradient(*s.scene, rq); });
  });
  return result;
}

py::dict backward_py(PyScene& s, const py::handle& d_image, const std::string& method, const PassArgs& a,
                     std::optional<uint64_t> adjoint_seed, const std::optional<std::vector<std::string>>& params) {
  const auto lock = lock_for_pass(s);
  gradient_pass(s, d_image, "d_image", nullptr, method, a, adjoint_seed, params);
  return gradients_of(*s.scene);
}

py::tuple grad_py(PyScene& s, const py::handle& target, const std::string& loss, const std::string& method,
                  const PassArgs& a, std::optional<uint64_t> adjoint_seed,
                  const std::optional<std::vector<std::string>>& params) {
  const auto lock = lock_for_pass(s);
  GradientResult r = gradient_pass(s, target, "target", &loss, method, a, adjoint_seed, params);
  return py::make_tuple(r.loss, gradients_of(*s.scene), image_array(std::move(r.image)));
}

double real_arg(const py::object& v, const std::string& name) {
  if (py::isinstance<py::bool_>(v) || !(py::isinstance<py::float_>(v) || py::isinstance<py::int_>(v) ||
                                        PyIndex_Check(v.ptr()) || py::hasattr(v, "__float__")))
    throw InputError(name + ": expected a number, got " + type_name(v) + " " + repr_of(v));
  const double x = PyFloat_AsDouble(v.ptr());
  if (PyErr_Occurred()) {
    PyErr_Clear();
    throw InputError(name + ": expected a number, got " + type_name(v) + " " + repr_of(v));
  }
  return x;
}

// The CLI's `backlight check` (tools/backlight.cpp): directional derivatives of the adjoint against
// central finite differences of the primal at the same seeds, one dict per direction.
py::list check_py(PyScene& s, const std::string& param, const py::object& target, const py::object& d_image,
                  const std::string& loss, const std::string& method, int directions, double eps, double tolerance,
                  uint64_t direction_seed, int seeds, const PassArgs& a, std::optional<uint64_t> adjoint_seed) {
  if (target.is_none() == d_image.is_none()) throw InputError("give exactly one of target and d_image");
  if (s.scene->params.find(param) < 0) throw InputError("param: unknown parameter '" + param + "' (see scene.params)");
  limits::require_at_most("directions", "direction count", uint64_t(directions), limits::kCheckDirections);
  if (!(eps > 0) || !std::isfinite(eps)) throw InputError("eps: expected a finite number > 0");
  if (!(tolerance >= 0) || !std::isfinite(tolerance)) throw InputError("tolerance: expected a finite number ≥ 0");
  const auto lock = lock_for_pass(s);
  refresh(s);
  CameraScope scope(*s.scene, a);
  Image img;
  GradientRequest rq =
      target.is_none()
          ? request_for(*s.scene, scope.camera(), d_image, "d_image", nullptr, method, a, adjoint_seed, img)
          : request_for(*s.scene, scope.camera(), target, "target", &loss, method, a, adjoint_seed, img);
  std::vector<CheckRow> rows;
  interruptible([&](const std::atomic<bool>* cancel) {
    rq.pass.cancel = cancel;
    rows = with_keyword_names(
        [&] { return directional_check(*s.scene, param, rq, directions, eps, direction_seed, seeds); });
  });
  py::list out;
  // The CLI's verdict (summarize_check): within the tolerance of the directions' RMS, or (over
  // several seeds) |z| below Student's t quantile of the 4σ tail.
  const CheckSummary verdict = summarize_check(rows, seeds, tolerance);
  for (size_t i = 0; i < rows.size(); ++i) {
    const CheckRow& r = rows[i];
    py::dict d;
    d["adjoint"] = r.adjoint;
    d["finite_difference"] = r.finite_difference;
    d["relative_error"] = r.relative_error;
    d["rms_relative_error"] = r.rms_relative_error;
    d["adjoint_stderr"] = r.adjoint_stderr;
    d["fd_stderr"] = r.fd_stderr;
    d["z"] = r.z;
    d["ok"] = bool(verdict.ok[i]);  // false for every row when nothing was compared
    d["nothing_compared"] = verdict.nothing_compared;
    // Over several seeds: the |z| accepted, and the smallest error of the adjoint's derivative along
    // this row's direction that the row would catch, over the RMS of the finite differences (the
    // CLI calls a pass in which any row's is above 0.25 INCONCLUSIVE).
    d["z_threshold"] = seeds > 1 ? verdict.threshold : std::numeric_limits<double>::quiet_NaN();
    d["resolution"] = verdict.resolution[i];
    out.append(d);
  }
  return out;
}

}  // namespace

PYBIND11_MODULE(_backlight, m) {
  m.doc() = "backlight: differentiable rendering with path replay backpropagation (see README)";
  py::module_::import("atexit").attr("register")(py::cpp_function(&stop_passes_at_exit));
  static py::exception<InputError> error(m, "Error", PyExc_ValueError);
  py::register_exception_translator([](std::exception_ptr p) {
    try {
      if (p) std::rethrow_exception(p);
    } catch (const InputError& e) {
      // Messages quote file contents and names, which need not be UTF-8: undecodable bytes are
      // shown as \xNN (PyErr_SetString left such a message empty).
      const std::string m = e.what();
      PyObject* text = PyUnicode_DecodeUTF8(m.data(), Py_ssize_t(m.size()), "backslashreplace");
      if (!text) {
        PyErr_Clear();
        text = PyUnicode_FromString("(an error message that could not be decoded)");
      }
      PyErr_SetObject(error.ptr(), text);
      Py_XDECREF(text);
    }
  });

  py::class_<PyScene>(m, "Scene", "A loaded scene (backlight.load). Parameters: scene.params.")
      .def_property_readonly(
          "params",
          [](py::object self) {
            PyScene& s = self.cast<PyScene&>();
            py::dict out;
            for (Param& p : s.scene->params.all()) {
              auto shape = shape_of(p);
              out[py::str(p.name)] = py::array_t<float>(shape, strides_of(shape), p.value.data(), self);
            }
            // Read-only: `scene.params[name] = value` on a fresh dict changed nothing, silently.
            return py::module_::import("types").attr("MappingProxyType")(out);
          },
          "Every parameter by name: a writable NumPy float32 view of the parameter store (no copy), in a read-only "
          "mapping (write into the views: scene.params[name][...] = value). Writes take effect at the next render; "
          "values are checked (finite, in range) then.")
      .def_property_readonly(
          "param_info",
          [](const PyScene& s) {
            py::dict out;
            for (const Param& p : s.scene->params.all())
              out[py::str(p.name)] = py::dict(py::arg("shape") = py::cast(p.shape), py::arg("lower") = p.lower,
                                              py::arg("upper") = p.upper);
            return out;
          },
          "Shape and valid range of every parameter")
      .def_property_readonly(
          "cameras",
          [](PyScene& s) {
            const auto lock = lock_for_pass(s);  // not a pass's temporary film size
            py::list out;
            for (const Camera& c : s.scene->cameras) out.append(py::make_tuple(c.width, c.height));
            return out;
          },
          "Film size (width, height) of each camera")
      .def_property_readonly(
          "spp", [](const PyScene& s) { return s.scene->settings.spp; }, "Samples per pixel of the scene file")
      .def_property_readonly(
          "seed", [](const PyScene& s) { return s.scene->settings.seed; }, "Sampler seed of the scene file")
      // The path is bytes (load takes os.fsencode of its argument); cast to str as UTF-8, a file name
      // with the byte 0xff made scene.path and repr(scene) raise UnicodeDecodeError.
      .def_property_readonly(
          "path", [](const PyScene& s) { return py::module_::import("os").attr("fsdecode")(py::bytes(s.path)); },
          "The scene file's name as os.fsdecode gives it (os.fsencode turns it back into the file system's bytes)")
      .def("__repr__", [](const PyScene& s) {
        return utf8_or_escaped("<backlight.Scene '" + s.path + "': " + std::to_string(s.scene->params.count()) +
                               " parameters, " + std::to_string(s.scene->cameras.size()) + " camera(s)>");
      });

  m.def("set_threads", &set_threads, py::arg("threads"),
        "Limits every pass to at most `threads` worker threads (1..65536; None: every core, the default), as the "
        "CLI's --threads. Process-wide, like torch.set_num_threads. Images are the same on any number of threads.");
  m.def("get_threads", &get_threads, "The number of worker threads passes may use (set_threads; else every core).");
  m.def("load", &load_py, py::arg("path"), py::arg("set") = py::none(), py::kw_only(),
        py::arg("max_depth") = py::none(), py::arg("rr_depth") = py::none(),
        "Loads a JSON, glTF or Mitsuba 3 XML scene. set: {name: value} overrides, as the CLI's --set (a number, a list "
        "of numbers, "
        "or an image file name); max_depth and rr_depth as the CLI's --max-depth and --rr-depth.");
  m.def(
      "render",
      [](const py::object& scene, const py::object& spp, const py::object& seed, const py::object& camera,
         const py::object& resolution) {
        return render_py(scene_arg(scene), pass_args(spp, seed, camera, resolution));
      },
      py::arg("scene"), py::kw_only(), py::arg("spp") = py::none(), py::arg("seed") = py::none(), py::arg("camera") = 0,
      py::arg("resolution") = py::none(),
      "Renders an image: float32 (height, width, 3). resolution = (width, height) overrides the camera's film for "
      "this call.");
  m.def(
      "backward",
      [](const py::object& scene, const py::handle& d_image, const py::object& method, const py::object& spp,
         const py::object& seed, const py::object& adjoint_seed, const py::object& camera, const py::object& resolution,
         const py::object& params) {
        PyScene& s = scene_arg(scene);
        return backward_py(s, d_image, str_arg(method, "method"), pass_args(spp, seed, camera, resolution),
                           seed_arg(adjoint_seed, "adjoint_seed"), names_arg(params, s.scene->params));
      },
      py::arg("scene"), py::arg("d_image"), py::kw_only(), py::arg("method") = "prb", py::arg("spp") = py::none(),
      py::arg("seed") = py::none(), py::arg("adjoint_seed") = py::none(), py::arg("camera") = 0,
      py::arg("resolution") = py::none(), py::arg("params") = py::none(),
      "Gradient of sum(d_image * render(scene)) with respect to the parameters (the names in params; by "
      "default every appearance parameter — materials, textures, emitters, media — not the geometry's poses, "
      "positions and cameras, which are differentiated when named): "
      "{name: float32 array shaped like the parameter}. d_image: float32 (height, width, 3). With adjoint_seed "
      "equal to seed (the default) it is the exact derivative of the image render(seed=seed) returns for emission, "
      "and for albedos and textures with Russian roulette off (load(..., rr_depth=0): roulette's continuation "
      "probability depends on them through the throughput); for albedos while roulette is on and for "
      "roughness-like parameters it is exact in expectation (sampling is detached).");
  m.def(
      "grad",
      [](const py::object& scene, const py::handle& target, const py::object& loss, const py::object& method,
         const py::object& spp, const py::object& seed, const py::object& adjoint_seed, const py::object& camera,
         const py::object& resolution, const py::object& params) {
        PyScene& s = scene_arg(scene);
        return grad_py(s, target, str_arg(loss, "loss"), str_arg(method, "method"),
                       pass_args(spp, seed, camera, resolution), seed_arg(adjoint_seed, "adjoint_seed"),
                       names_arg(params, s.scene->params));
      },
      py::arg("scene"), py::arg("target"), py::kw_only(), py::arg("loss") = "l2", py::arg("method") = "prb",
      py::arg("spp") = py::none(), py::arg("seed") = py::none(), py::arg("adjoint_seed") = py::none(),
      py::arg("camera") = 0, py::arg("resolution") = py::none(), py::arg("params") = py::none(),
      "Loss of the render against target (l2, l1 or rel_l2) and its gradient: (loss, {name: gradient}, image).");
  m.def(
      "check",
      [](const py::object& scene, const py::object& param, const py::object& target, const py::object& d_image,
         const py::object& loss, const py::object& method, const py::object& directions, const py::object& eps,
         const py::object& tolerance, const py::object& direction_seed, const py::object& seeds, const py::object& spp,
         const py::object& seed, const py::object& adjoint_seed, const py::object& camera,
         const py::object& resolution) {
        return check_py(scene_arg(scene), str_arg(param, "param"), target, d_image, str_arg(loss, "loss"),
                        str_arg(method, "method"), required_int_arg(directions, "directions", 1, INT32_MAX),
                        real_arg(eps, "eps"), real_arg(tolerance, "tolerance"),
                        required_seed_arg(direction_seed, "direction_seed"),
                        required_int_arg(seeds, "seeds", 1, 1 << 16), pass_args(spp, seed, camera, resolution),
                        seed_arg(adjoint_seed, "adjoint_seed"));
      },
      py::arg("scene"), py::arg("param"), py::kw_only(), py::arg("target") = py::none(),
      py::arg("d_image") = py::none(), py::arg("loss") = "l2", py::arg("method") = "prb", py::arg("directions") = 4,
      py::arg("eps") = 1e-2, py::arg("tolerance") = 1e-2, py::arg("direction_seed") = 1, py::arg("seeds") = 1,
      py::arg("spp") = py::none(), py::arg("seed") = py::none(), py::arg("adjoint_seed") = py::none(),
      py::arg("camera") = 0, py::arg("resolution") = py::none(),
      "The CLI's `backlight check`: for `directions` random directions v (i.i.d. standard normal, one per welded "
      "position for vertex positions, seeded by "
      "direction_seed), the adjoint's directional derivative <grad, v> against the central finite difference "
      "(loss(theta + eps v) - loss(theta - eps v)) / 2 eps of renders at the same seed; the loss against target "
      "(loss=l2, l1 or rel_l2), or sum(d_image * I) with d_image. seeds > 1 averages both over seeds seed, seed+1, "
      "... (for parameters sampling depends on, and geometry). Returns one dict per direction: adjoint, "
      "finite_difference, relative_error (|adjoint - finite_difference| / |finite_difference|), rms_relative_error "
      "(the same over the RMS of finite_difference over all directions), adjoint_stderr, fd_stderr, z (NaN for one "
      "seed), ok (rms_relative_error <= tolerance, or over several seeds |z| < z_threshold, Student's t quantile of "
      "the 4-sigma tail; false in every row with nothing_compared, when neither side changes in any direction: the "
      "parameter does not reach the image) and resolution (over several seeds: the smallest error of the adjoint's "
      "derivative along "
      "the row's direction that the row fails, over that RMS; above 0.25 in any row, the CLI calls a pass "
      "INCONCLUSIVE). The parameter's values are restored afterwards.");
}
