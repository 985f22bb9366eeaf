/*
 * radaredge_run: run any radaredge .onnx from C, as radaredge.runtime does in Python.
 *
 *   radaredge_run [--threads N] [--timestamps t0,t1,...] [--out DIR] [--no-checks] MODEL.onnx SCAN.bin...
 *
 * One SCAN.bin per frame the graph takes, oldest first: little-endian float32 rows with the
 * card's feature columns (radaredge.features in the graph's metadata), e.g. x, y, z, v_r, rcs.
 * Timestamps are seconds (any epoch: they are made relative in double precision before the graph
 * sees float32); without them the frames are 1 / frame_rate apart.
 *
 * What it does, in radaredge.runtime's order: reads the card, the features and the input roles
 * from the metadata; checks every scan (whole rows, finite values, at most max_points_per_frame
 * points) and the timestamps (strictly increasing), naming the file, point and column of a
 * problem; runs one onnxruntime session with radaredge's options (intra-op threads N, one
 * inter-op thread, sequential, all graph optimisations, session.force_spinning_stop = 1); reports
 * the graph's input_flags output bit by bit (radaredge.input_flags in the metadata); acts on the
 * flag outputs the model declares (radaredge.checks: e.g. MAFF-Net's spa_overflow is an error,
 * as radaredge.runtime's CapacityError, and a warning is printed); writes each output as
 * DIR/<name>.bin (raw, native byte order) and DIR/summary.json (names, types, shapes).
 * --no-checks skips the client's own checks and the declared ones, so the outputs and the
 * graph's input_flags show what it did.
 *
 * Exit codes: 0 success (input_flags bits that only inform, e.g. points out of range, and
 * declared warnings are printed on stderr), 1 the graph flagged wrong input (bit 1 non_finite
 * or 2 time_order, which reach the graph only with --no-checks, or a bit the graph's
 * radaredge.input_errors adds, e.g. 32 implausible for a card that refuses such points), 2 bad input, an error a
 * declared check raised (no outputs are written then) or a model that is not a radaredge
 * export, reported as one "error: ..." line on stderr.
 */
#include <errno.h>
#include <math.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include <onnxruntime_c_api.h>

#define MAX_ITEMS 64
#define INPUT_ERRORS 3      /* input_flags bits 1 (non_finite) and 2 (time_order): the input was wrong,
                               unless the graph's radaredge.input_errors names other bits */
#define PERIOD_FACTOR 10.0  /* radaredge.runtime's: frame times this far off the card's period are refused */
#define MAX_NAME 128

static const OrtApi *ort;

static void fail(const char *fmt, ...) {
    va_list ap;
    va_start(ap, fmt);
    fputs("error: ", stderr);
    vfprintf(stderr, fmt, ap);
    fputc('\n', stderr);
    va_end(ap);
    exit(2);
}

static void check(OrtStatus *status, const char *what) {
    if (status != NULL) {
        char message[512];
        snprintf(message, sizeof message, "%s", ort->GetErrorMessage(status));
        ort->ReleaseStatus(status);
        fail("onnxruntime: %s: %s", what, message);
    }
}

/* Just after the colon of the member "key": of json (a name in a list is no member), or NULL. */
static const char *json_key(const char *json, const char *key) {
    char quoted[MAX_NAME + 4];
    snprintf(quoted, sizeof quoted, "\"%s\"", key);
    for (const char *p = strstr(json, quoted); p != NULL; p = strstr(p + 1, quoted)) {
        const char *q = p + strlen(quoted);
        while (*q == ' ') q++;
        if (*q == ':') return q + 1;
    }
    return NULL;
}

/* The strings of the JSON array that follows "key": in json (or the whole value when key is
 * NULL). radaredge writes names without escapes, so a quote always ends a string. */
static int json_strings(const char *json, const char *key, char out[][MAX_NAME], int max) {
    const char *p = json;
    if (key != NULL) {
        p = json_key(json, key);
        if (p == NULL) return -1;
    }
    p = strchr(p, '[');
    if (p == NULL) return -1;
    int n = 0;
    for (p++; *p != '\0' && *p != ']'; p++) {
        if (*p != '"') continue;
        const char *end = strchr(p + 1, '"');
        if (end == NULL || n == max || end - p - 1 >= MAX_NAME) return -1;
        memcpy(out[n], p + 1, (size_t)(end - p - 1));
        out[n][end - p - 1] = '\0';
        n++;
        p = end;
    }
    return n;
}

/* The string value of "key": "value" in json; "" when it is null or absent. */
static void json_string(const char *json, const char *key, char *out, size_t size) {
    out[0] = '\0';
    const char *p = json_key(json, key);
    if (p == NULL) return;
    while (*p == ' ') p++;
    if (*p != '"') return;
    const char *end = strchr(p + 1, '"');
    if (end == NULL || (size_t)(end - p - 1) >= size) return;
    memcpy(out, p + 1, (size_t)(end - p - 1));
    out[end - p - 1] = '\0';
}

/* The JSON string that starts at p (at its opening quote) decoded into out (\uXXXX outside ASCII
 * as '?'); the position after its closing quote, or NULL when it is not a whole string. */
static const char *json_decode(const char *p, char *out, size_t size) {
    size_t n = 0;
    if (*p != '"') return NULL;
    for (p++; *p != '\0' && *p != '"'; p++) {
        char c = *p;
        if (c == '\\') {
            p++;
            switch (*p) {
            case 'n': c = '\n'; break;
            case 't': c = '\t'; break;
            case 'u': {
                unsigned code = 0;
                for (int i = 1; i <= 4; i++) {
                    char h = p[i];
                    if (!((h >= '0' && h <= '9') || (h >= 'a' && h <= 'f') || (h >= 'A' && h <= 'F'))) return NULL;
                    code = code * 16 + (unsigned)(h <= '9' ? h - '0' : (h | 32) - 'a' + 10);
                }
                c = (code < 128) ? (char)code : '?';
                p += 4;
                break;
            }
            case '\0': return NULL;
            default: c = *p;          /* \" \\ \/ */
            }
        }
        if (n + 1 < size) out[n++] = c;
    }
    out[n] = '\0';
    return *p == '"' ? p + 1 : NULL;
}

/* A flag output the runtime acts on (radaredge.checks): when output `output` equals
 * `fails_when`, `message` is an error (severity "error") or a warning. */
typedef struct {
    char output[MAX_NAME], severity[16], message[1024];
    int fails_when;
} Check;

static const char *skip_space(const char *p) {
    while (*p == ' ' || *p == ',' || *p == '\n') p++;
    return p;
}

/* The checks of the radaredge.checks JSON list (objects of output, fails_when, severity and
 * message); -1 when it cannot be read. */
static int read_checks(const char *json, Check *out, int max) {
    const char *p = skip_space(json);
    int n = 0;
    if (*p++ != '[') return -1;
    for (p = skip_space(p); *p == '{'; p = skip_space(p)) {
        if (n == max) return -1;
        Check *c = &out[n];
        memset(c, 0, sizeof *c);
        for (p = skip_space(p + 1); *p != '}'; p = skip_space(p)) {
            char key[32];
            p = json_decode(p, key, sizeof key);
            if (p == NULL) return -1;
            p = skip_space(p);
            if (*p++ != ':') return -1;
            while (*p == ' ') p++;
            if (strcmp(key, "output") == 0) p = json_decode(p, c->output, sizeof c->output);
            else if (strcmp(key, "severity") == 0) p = json_decode(p, c->severity, sizeof c->severity);
            else if (strcmp(key, "message") == 0) p = json_decode(p, c->message, sizeof c->message);
            else if (strcmp(key, "fails_when") == 0 && strncmp(p, "true", 4) == 0) c->fails_when = 1, p += 4;
            else if (strcmp(key, "fails_when") == 0 && strncmp(p, "false", 5) == 0) c->fails_when = 0, p += 5;
            else return -1;
            if (p == NULL) return -1;
        }
        if (c->output[0] == '\0' || (strcmp(c->severity, "error") != 0 && strcmp(c->severity, "warn") != 0)) return -1;
        n++;
        p++;
    }
    return *p == ']' ? n : -1;
}

/* A top-level number "key: value" of the card's YAML, or fallback when the card has none. */
static double card_number(const char *yaml, const char *key, double fallback) {
    size_t n = strlen(key);
    for (const char *line = yaml; line != NULL && *line != '\0'; line = strchr(line, '\n')) {
        if (*line == '\n') line++;
        if (strncmp(line, key, n) == 0 && line[n] == ':') return strtod(line + n + 1, NULL);
    }
    return fallback;
}

/* The value of a one-element output as a double; 0 (and *ok = 0) when it has more elements or a
 * type this client does not read. */
static double output_scalar(OrtValue *value, int *is_integer, int *ok) {
    OrtTensorTypeAndShapeInfo *info;
    ONNXTensorElementDataType type;
    size_t count;
    void *data;
    check(ort->GetTensorTypeAndShape(value, &info), "output type");
    check(ort->GetTensorElementType(info, &type), "output type");
    check(ort->GetTensorShapeElementCount(info, &count), "output shape");
    ort->ReleaseTensorTypeAndShapeInfo(info);
    check(ort->GetTensorMutableData(value, &data), "output data");
    *ok = count == 1;
    *is_integer = 1;
    if (count != 1) return 0.0;
    switch (type) {
    case ONNX_TENSOR_ELEMENT_DATA_TYPE_BOOL: return *(const uint8_t *)data ? 1.0 : 0.0;
    case ONNX_TENSOR_ELEMENT_DATA_TYPE_INT32: return *(const int32_t *)data;
    case ONNX_TENSOR_ELEMENT_DATA_TYPE_INT64: return (double)*(const int64_t *)data;
    case ONNX_TENSOR_ELEMENT_DATA_TYPE_FLOAT: *is_integer = 0; return *(const float *)data;
    case ONNX_TENSOR_ELEMENT_DATA_TYPE_DOUBLE: *is_integer = 0; return *(const double *)data;
    default: *ok = 0; return 0.0;
    }
}

/* Acts on the declared checks after a run, as radaredge.runtime does: a check whose output equals
 * fails_when fails (severity error) or prints a warning; "{name}" in its message becomes the
 * value of the one-element output `name`. */
static void apply_checks(const Check *checks, int n_checks, char **names, OrtValue **outputs, size_t n_out) {
    for (int c = 0; c < n_checks; c++) {
        size_t i = 0;
        while (i < n_out && strcmp(names[i], checks[c].output) != 0) i++;
        int is_integer, ok;
        if (i == n_out) continue;                                     /* the output is absent: no check */
        double flag = output_scalar(outputs[i], &is_integer, &ok);
        if (!ok || (flag != 0.0) != checks[c].fails_when) continue;
        char message[2048];
        size_t n = 0;
        for (const char *p = checks[c].message; *p != '\0' && n + 64 < sizeof message; p++) {
            const char *close = (*p == '{') ? strchr(p, '}') : NULL;
            size_t j = n_out;
            if (close != NULL && (size_t)(close - p - 1) < MAX_NAME) {
                char name[MAX_NAME];
                memcpy(name, p + 1, (size_t)(close - p - 1));
                name[close - p - 1] = '\0';
                for (j = 0; j < n_out && strcmp(names[j], name) != 0; j++) {}
            }
            double v = (j < n_out) ? output_scalar(outputs[j], &is_integer, &ok) : 0.0;
            if (j < n_out && ok) {
                n += (size_t)snprintf(message + n, sizeof message - n, is_integer ? "%.0f" : "%.9g", v);
                p = close;
            } else {
                message[n++] = *p;
            }
        }
        message[n] = '\0';
        if (strcmp(checks[c].severity, "error") == 0) fail("%s", message);
        fprintf(stderr, "warning: %s\n", message);
    }
}

static char *metadata(OrtModelMetadata *meta, OrtAllocator *alloc, const char *key, const char *model, int required) {
    char *value = NULL;
    check(ort->ModelMetadataLookupCustomMetadataMap(meta, alloc, key, &value), "reading the metadata");
    if (value == NULL && required)
        fail("%s is not a radaredge export: its metadata has no %s entry", model, key);
    return value;
}

typedef struct {
    float *rows;
    int64_t n;
} Scan;

/* Reads path as float32 rows of `columns` columns, checked as radaredge.runtime checks a frame. */
static Scan read_scan(const char *path, int frame, int columns, char names[][MAX_NAME], int64_t max_points,
                      int checks) {
    FILE *f = fopen(path, "rb");
    if (f == NULL) fail("%s: %s", path, strerror(errno));
    if (fseek(f, 0, SEEK_END) != 0) fail("%s: cannot seek", path);
    long bytes = ftell(f);
    rewind(f);
    long row = (long)columns * (long)sizeof(float);
    if (bytes < 0 || bytes % row != 0)
        fail("%s: %ld bytes is not a whole number of rows of %d float32 columns (%ld bytes each)", path, bytes,
             columns, row);
    Scan s = {NULL, bytes / row};
    if (checks && s.n > max_points)
        fail("frame %d (%s): %lld points, more than the card's max_points_per_frame %lld", frame, path,
             (long long)s.n, (long long)max_points);
    s.rows = malloc(bytes > 0 ? (size_t)bytes : sizeof(float));
    if (s.rows == NULL) fail("%s: out of memory", path);
    if (bytes > 0 && fread(s.rows, 1, (size_t)bytes, f) != (size_t)bytes) fail("%s: short read", path);
    fclose(f);
    if (checks) {
        for (int64_t i = 0; i < s.n * columns; i++) {
            if (!isfinite(s.rows[i]))
                fail("frame %d (%s): non-finite value %g at point %lld, column '%s'", frame, path, (double)s.rows[i],
                     (long long)(i / columns), names[i % columns]);
        }
    }
    return s;
}

static const char *type_name(ONNXTensorElementDataType t, size_t *size) {
    switch (t) {
        case ONNX_TENSOR_ELEMENT_DATA_TYPE_FLOAT: *size = 4; return "float32";
        case ONNX_TENSOR_ELEMENT_DATA_TYPE_DOUBLE: *size = 8; return "float64";
        case ONNX_TENSOR_ELEMENT_DATA_TYPE_INT64: *size = 8; return "int64";
        case ONNX_TENSOR_ELEMENT_DATA_TYPE_INT32: *size = 4; return "int32";
        case ONNX_TENSOR_ELEMENT_DATA_TYPE_BOOL: *size = 1; return "bool";
        case ONNX_TENSOR_ELEMENT_DATA_TYPE_UINT8: *size = 1; return "uint8";
        default: *size = 0; return "unsupported";
    }
}

static void usage(void) {
    fail("usage: radaredge_run [--threads N] [--timestamps t0,t1,...] [--out DIR] [--no-checks] MODEL.onnx SCAN.bin...");
}

int main(int argc, char **argv) {
    int threads = 2, checks = 1, n_stamps = 0;
    double stamps[MAX_ITEMS];
    const char *out_dir = ".";
    int arg = 1;
    for (; arg < argc && strncmp(argv[arg], "--", 2) == 0; arg++) {
        if (strcmp(argv[arg], "--threads") == 0 && arg + 1 < argc) {
            char *end;
            long t = strtol(argv[++arg], &end, 10);
            long most = 4 * sysconf(_SC_NPROCESSORS_ONLN);          /* radaredge's bound: 4 x the cores */
            if (most < 4) most = 4;
            if (*end != '\0' || t < 1 || t > most)
                fail("--threads: expected an integer from 1 to %ld (4 x the cores), got %s", most, argv[arg]);
            threads = (int)t;
        } else if (strcmp(argv[arg], "--timestamps") == 0 && arg + 1 < argc) {
            for (char *p = argv[++arg]; *p != '\0' && n_stamps < MAX_ITEMS;) {
                char *end;
                stamps[n_stamps++] = strtod(p, &end);
                if (end == p || !isfinite(stamps[n_stamps - 1])) fail("--timestamps: cannot read '%s' as seconds", p);
                p = (*end == ',') ? end + 1 : end;
            }
        } else if (strcmp(argv[arg], "--out") == 0 && arg + 1 < argc) {
            out_dir = argv[++arg];
        } else if (strcmp(argv[arg], "--no-checks") == 0) {
            checks = 0;
        } else {
            usage();
        }
    }
    if (arg >= argc) usage();
    const char *model = argv[arg++];

    ort = OrtGetApiBase()->GetApi(ORT_API_VERSION);
    if (ort == NULL) fail("this onnxruntime library does not provide C API version %d", ORT_API_VERSION);
    OrtEnv *env;
    check(ort->CreateEnv(ORT_LOGGING_LEVEL_ERROR, "radaredge", &env), "creating the environment");
    OrtSessionOptions *opts;
    check(ort->CreateSessionOptions(&opts), "session options");
    check(ort->SetIntraOpNumThreads(opts, threads), "intra-op threads");
    check(ort->SetInterOpNumThreads(opts, 1), "inter-op threads");
    check(ort->SetSessionExecutionMode(opts, ORT_SEQUENTIAL), "execution mode");
    check(ort->SetSessionGraphOptimizationLevel(opts, ORT_ENABLE_ALL), "optimisation level");
    check(ort->SetSessionLogSeverityLevel(opts, 3), "log level");
    /* worker threads stop spinning when a run returns: the app needs the cores between scans */
    check(ort->AddSessionConfigEntry(opts, "session.force_spinning_stop", "1"), "force_spinning_stop");
    OrtSession *session;
    FILE *probe = fopen(model, "rb");
    if (probe == NULL) fail("%s: %s", model, strerror(errno));
    fclose(probe);
    check(ort->CreateSession(env, model, opts, &session), model);
    OrtAllocator *alloc;
    check(ort->GetAllocatorWithDefaultOptions(&alloc), "allocator");

    OrtModelMetadata *meta;
    check(ort->SessionGetModelMetadata(session, &meta), "metadata");
    char *card = metadata(meta, alloc, "radaredge.card", model, 1);
    char *features_json = metadata(meta, alloc, "radaredge.features", model, 1);
    char *inputs_json = metadata(meta, alloc, "radaredge.inputs", model, 1);
    char *flags_json = metadata(meta, alloc, "radaredge.input_flags", model, 0);
    char *checks_json = metadata(meta, alloc, "radaredge.checks", model, 0);
    char *errors_text = metadata(meta, alloc, "radaredge.input_errors", model, 0);
    long input_errors = INPUT_ERRORS;
    if (errors_text != NULL) {
        char *end;
        input_errors = strtol(errors_text, &end, 10);
        if (*end != '\0' || input_errors < 0 || input_errors > 0x7fffffffL)
            fail("%s: unreadable radaredge.input_errors metadata '%s'", model, errors_text);
        check(ort->AllocatorFree(alloc, errors_text), "free");
    }
    Check declared[8];
    int n_checks = (checks_json != NULL) ? read_checks(checks_json, declared, 8) : 0;
    if (n_checks < 0) fail("%s: unreadable radaredge.checks metadata", model);
    char features[MAX_ITEMS][MAX_NAME], frames[MAX_ITEMS][MAX_NAME], stamps_input[MAX_NAME];
    int n_features = json_strings(features_json, NULL, features, MAX_ITEMS);
    int n_frames = json_strings(inputs_json, "frames", frames, MAX_ITEMS);
    json_string(inputs_json, "timestamps", stamps_input, sizeof stamps_input);
    if (n_features < 1 || n_frames < 0) fail("%s: unreadable radaredge.features / radaredge.inputs metadata", model);
    if (n_frames == 0) fail("%s takes no point-cloud frames (a Des4Pos text or fine-stage graph)", model);
    double frame_rate = card_number(card, "frame_rate", 10.0);
    double max_points_card = card_number(card, "max_points_per_frame", 65536.0);
    if (!(max_points_card >= 1.0 && max_points_card <= 16777216.0))   /* the card parser's range */
        fail("%s: max_points_per_frame %.9g in its card is outside 1..16777216", model, max_points_card);
    int64_t max_points = (int64_t)max_points_card;
    printf("model %s: %d frame(s) of [N, %d] float32 columns", model, n_frames, n_features);
    for (int i = 0; i < n_features; i++) printf("%s%s", i ? ", " : " ", features[i]);
    printf("\ncard:\n%s", card);

    if (argc - arg != n_frames) fail("%s takes %d frame(s) (oldest first), got %d scan file(s)", model, n_frames, argc - arg);
    Scan scans[MAX_ITEMS];
    for (int k = 0; k < n_frames; k++) scans[k] = read_scan(argv[arg + k], k, n_features, features, max_points, checks);

    float rel[MAX_ITEMS];
    if (n_stamps == 0) {
        for (int k = 0; k < n_frames; k++) rel[k] = (float)(k / frame_rate);
    } else {
        if (n_stamps != n_frames) fail("--timestamps: expected %d values in seconds, got %d", n_frames, n_stamps);
        for (int k = 1; k < n_frames && checks; k++)
            if (!(stamps[k] > stamps[k - 1]))
                fail("timestamps must increase strictly (oldest frame first), got %.9g after %.9g", stamps[k],
                     stamps[k - 1]);
        for (int k = 1; k < n_frames && checks; k++) {         /* radaredge.runtime: PERIOD_FACTOR, seconds */
            double gap = stamps[k] - stamps[k - 1], period = 1.0 / frame_rate;
            if (gap > period * PERIOD_FACTOR || gap < period / PERIOD_FACTOR)
                fail("timestamps: frames %d and %d are %g s apart; the card records at %g Hz, and frame times more "
                     "than %gx off its period are refused (timestamps are seconds)", k - 1, k, gap, frame_rate,
                     PERIOD_FACTOR);
        }
        for (int k = 0; k < n_frames; k++) rel[k] = (float)(stamps[k] - stamps[0]);     /* differences in double */
        for (int k = 1; k < n_frames && checks; k++)           /* radaredge.runtime: the graph's flag, an error */
            if (!(rel[k] > rel[k - 1]))
                fail("timestamps %.9g and %.9g are closer than the graph's float32 seconds resolve", stamps[k - 1],
                     stamps[k]);
    }

    OrtMemoryInfo *mem;
    check(ort->CreateCpuMemoryInfo(OrtArenaAllocator, OrtMemTypeDefault, &mem), "memory info");
    size_t n_inputs;
    check(ort->SessionGetInputCount(session, &n_inputs), "input count");
    if (n_inputs != (size_t)n_frames + (stamps_input[0] ? 1u : 0u))
        fail("%s has %zu inputs; its metadata names %d frame input(s)%s", model, n_inputs, n_frames,
             stamps_input[0] ? " and timestamps" : "");
    const char *input_names[MAX_ITEMS + 1];
    OrtValue *inputs[MAX_ITEMS + 1];
    for (int k = 0; k < n_frames; k++) {
        int64_t shape[2] = {scans[k].n, n_features};
        input_names[k] = frames[k];
        check(ort->CreateTensorWithDataAsOrtValue(mem, scans[k].rows, (size_t)(scans[k].n * n_features) * sizeof(float),
                                                  shape, 2, ONNX_TENSOR_ELEMENT_DATA_TYPE_FLOAT, &inputs[k]), frames[k]);
    }
    size_t n_in = (size_t)n_frames;
    if (stamps_input[0]) {
        int64_t shape[1] = {n_frames};
        input_names[n_in] = stamps_input;
        check(ort->CreateTensorWithDataAsOrtValue(mem, rel, (size_t)n_frames * sizeof(float), shape, 1,
                                                  ONNX_TENSOR_ELEMENT_DATA_TYPE_FLOAT, &inputs[n_in]), stamps_input);
        n_in++;
    }

    size_t n_out;
    check(ort->SessionGetOutputCount(session, &n_out), "output count");
    if (n_out > MAX_ITEMS) fail("%s has %zu outputs; this client takes at most %d", model, n_out, MAX_ITEMS);
    char *output_names[MAX_ITEMS];
    OrtValue *outputs[MAX_ITEMS] = {0};
    for (size_t i = 0; i < n_out; i++) check(ort->SessionGetOutputName(session, i, alloc, &output_names[i]), "output name");
    check(ort->Run(session, NULL, input_names, (const OrtValue *const *)inputs, n_in,
                   (const char *const *)output_names, n_out, outputs), "run");
    if (checks) apply_checks(declared, n_checks, output_names, outputs, n_out);

    char path[4096];
    snprintf(path, sizeof path, "%s/summary.json", out_dir);
    FILE *summary = fopen(path, "w");
    if (summary == NULL) fail("%s: %s", path, strerror(errno));
    fprintf(summary, "{\"model\": \"%s\", \"threads\": %d, \"outputs\": [", model, threads);
    int flagged = 0;
    for (size_t i = 0; i < n_out; i++) {
        OrtTensorTypeAndShapeInfo *info;
        check(ort->GetTensorTypeAndShape(outputs[i], &info), output_names[i]);
        ONNXTensorElementDataType type;
        size_t rank, count, size;
        int64_t dims[16];
        check(ort->GetTensorElementType(info, &type), output_names[i]);
        check(ort->GetDimensionsCount(info, &rank), output_names[i]);
        if (rank > 16) fail("output %s has rank %zu", output_names[i], rank);
        check(ort->GetDimensions(info, dims, rank), output_names[i]);
        check(ort->GetTensorShapeElementCount(info, &count), output_names[i]);
        ort->ReleaseTensorTypeAndShapeInfo(info);
        const char *tname = type_name(type, &size);
        if (size == 0) fail("output %s has element type %d, which this client does not write", output_names[i], (int)type);
        void *data;
        check(ort->GetTensorMutableData(outputs[i], &data), output_names[i]);
        snprintf(path, sizeof path, "%s/%s.bin", out_dir, output_names[i]);
        FILE *f = fopen(path, "wb");
        if (f == NULL || (count > 0 && fwrite(data, size, count, f) != count)) fail("%s: cannot write", path);
        fclose(f);
        fprintf(summary, "%s{\"name\": \"%s\", \"dtype\": \"%s\", \"shape\": [", i ? ", " : "", output_names[i], tname);
        for (size_t d = 0; d < rank; d++) fprintf(summary, "%s%lld", d ? ", " : "", (long long)dims[d]);
        fprintf(summary, "]}");
        if (strcmp(output_names[i], "input_flags") == 0 && type == ONNX_TENSOR_ELEMENT_DATA_TYPE_INT32) {
            const int32_t *flags = data;
            for (size_t k = 0; k < count; k++) {
                for (int bit = 0; bit < 31; bit++) {
                    if (!(flags[k] & (1 << bit))) continue;
                    char key[16], meaning[256] = "undocumented bit";
                    snprintf(key, sizeof key, "%d", 1 << bit);
                    if (flags_json != NULL) json_string(flags_json, key, meaning, sizeof meaning);
                    fprintf(stderr, "input_flags: frame %zu: bit %d (%s): %s\n", k, bit, key, meaning);
                    if ((1L << bit) & input_errors) flagged = 1;
                }
            }
        }
    }
    fprintf(summary, "]}\n");
    fclose(summary);
    printf("ran %s on %d thread(s); wrote %zu output(s) to %s\n", model, threads, n_out, out_dir);

    for (size_t i = 0; i < n_out; i++) {
        ort->ReleaseValue(outputs[i]);
        check(ort->AllocatorFree(alloc, output_names[i]), "free");
    }
    for (size_t i = 0; i < n_in; i++) ort->ReleaseValue(inputs[i]);
    for (int k = 0; k < n_frames; k++) free(scans[k].rows);
    check(ort->AllocatorFree(alloc, card), "free");
    check(ort->AllocatorFree(alloc, features_json), "free");
    check(ort->AllocatorFree(alloc, inputs_json), "free");
    if (flags_json != NULL) check(ort->AllocatorFree(alloc, flags_json), "free");
    if (checks_json != NULL) check(ort->AllocatorFree(alloc, checks_json), "free");
    ort->ReleaseModelMetadata(meta);
    ort->ReleaseMemoryInfo(mem);
    ort->ReleaseSession(session);
    ort->ReleaseSessionOptions(opts);
    ort->ReleaseEnv(env);
    return flagged ? 1 : 0;
}
