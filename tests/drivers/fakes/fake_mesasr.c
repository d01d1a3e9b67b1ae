/* A fake libmesasr.so for testing drivers/sr4000_mesasr.py without a camera.
 *
 * It has the real library's C signatures (libMesaSR.h / definesSR.h) and answers with data a test
 * can recognise, so a wrong ctypes declaration, stride or axis conversion shows up as wrong numbers:
 *   distance[r][c]   = 100 r + c + 1
 *   amplitude[r][c]  = 1000 + c + 7 * (frames acquired so far)
 *   confidence[r][c] = 0xFFFF - 10 r                (only with AM_CONF_MAP set)
 *   SR_CoordTrfFlt, MESA axes: X = 0.001 c, Y = 0.002 r, Z = distance * 5 / 0xFFFF
 * Auto exposure (SR_SetAutoExposure with min != 255) halves the distance between the integration
 * time and 80 at each SR_Acquire, so it settles after a few frames.
 *
 * Every call is recorded as one text line, read back with FAKE_CallLog(); FAKE_SetOpenResult and
 * FAKE_SetAcquireResult make opening or acquiring fail.
 *
 * Build: gcc -shared -fPIC -o libmesasr.so fake_mesasr.c
 */
#include <stdarg.h>
#include <stdio.h>
#include <string.h>

#define ROWS 144
#define COLS 176
#define AM_CONF_MAP 0x100
#define FAKE_SERIAL 0x4000ABCDu

typedef struct _ImgEntry {
    int imgType;          /* enum ImgType: 0 distance, 1 amplitude, 8 confidence map */
    int dataType;         /* enum DataType: 3 unsigned short */
    void *data;
    unsigned short width;
    unsigned short height;
} ImgEntry;

typedef struct FakeCamera {
    unsigned int serial;
    int mode;
    unsigned char integration_time;
    unsigned short amplitude_threshold;
    int modulation;
    int timeout_ms;
    unsigned char auto_exposure[4];
    int frames;
} FakeCamera;
typedef FakeCamera *SRCAM;

static FakeCamera camera;
static unsigned short distance_image[ROWS * COLS];
static unsigned short amplitude_image[ROWS * COLS];
static unsigned short confidence_image[ROWS * COLS];
static ImgEntry entries[3];
static char call_log[1 << 16];
static size_t log_length;
static int open_result = 1;
static int acquire_result = 0;   /* 0: succeed; negative: SR_Acquire returns it */

static void record(const char *format, ...)
{
    va_list args;
    int written;
    if (log_length >= sizeof(call_log) - 128)
        return;
    va_start(args, format);
    written = vsnprintf(call_log + log_length, sizeof(call_log) - log_length, format, args);
    va_end(args);
    if (written > 0)
        log_length += (size_t)written;
    call_log[log_length++] = '\n';
    call_log[log_length] = '\0';
}

/* ---- test controls --------------------------------------------------------------------- */
const char *FAKE_CallLog(void) { return call_log; }
void FAKE_ClearLog(void) { log_length = 0; call_log[0] = '\0'; }
void FAKE_SetOpenResult(int result) { open_result = result; }
void FAKE_SetAcquireResult(int result) { acquire_result = result; }

/* ---- opening and closing ----------------------------------------------------------------- */
static int open_camera(SRCAM *handle, unsigned int serial)
{
    if (open_result <= 0) {
        *handle = 0;
        return open_result;
    }
    memset(&camera, 0, sizeof(camera));
    camera.serial = serial ? serial : FAKE_SERIAL;
    camera.integration_time = 30;
    camera.modulation = 1;
    camera.auto_exposure[0] = 255;
    *handle = &camera;
    return 1;
}

int SR_OpenUSB(SRCAM *handle, unsigned int serial)
{
    record("SR_OpenUSB %#x", serial);
    return open_camera(handle, serial);
}

int SR_OpenETH(SRCAM *handle, const char *address)
{
    record("SR_OpenETH %s", address);
    return open_camera(handle, 0);
}

int SR_Close(SRCAM cam)
{
    record("SR_Close");
    return cam == &camera ? 0 : -1;
}

/* ---- settings ---------------------------------------------------------------------------- */
int SR_SetIntegrationTime(SRCAM cam, unsigned char value)
{
    record("SR_SetIntegrationTime %u", value);
    cam->integration_time = value;
    return 0;
}

unsigned char SR_GetIntegrationTime(SRCAM cam) { return cam->integration_time; }

int SR_SetAmplitudeThreshold(SRCAM cam, unsigned short value)
{
    record("SR_SetAmplitudeThreshold %u", value);
    cam->amplitude_threshold = value;
    return 0;
}

unsigned short SR_GetAmplitudeThreshold(SRCAM cam) { return cam->amplitude_threshold; }

int SR_SetModulationFrequency(SRCAM cam, int frequency)
{
    record("SR_SetModulationFrequency %d", frequency);
    cam->modulation = frequency;
    return 0;
}

int SR_GetModulationFrequency(SRCAM cam) { return cam->modulation; }

int SR_SetAutoExposure(SRCAM cam, unsigned char min_time, unsigned char max_time,
                       unsigned char percent_over_pos, unsigned char desired_pos)
{
    record("SR_SetAutoExposure %u %u %u %u", min_time, max_time, percent_over_pos, desired_pos);
    cam->auto_exposure[0] = min_time;
    cam->auto_exposure[1] = max_time;
    cam->auto_exposure[2] = percent_over_pos;
    cam->auto_exposure[3] = desired_pos;
    return 0;
}

int SR_SetMode(SRCAM cam, int mode)
{
    record("SR_SetMode %#x", mode);
    cam->mode = mode;
    return 0;
}

int SR_GetMode(SRCAM cam) { return cam->mode; }

void SR_SetTimeout(SRCAM cam, int ms)
{
    record("SR_SetTimeout %d", ms);
    cam->timeout_ms = ms;
}

unsigned int SR_ReadSerial(SRCAM cam) { return cam->serial; }
unsigned int SR_GetRows(SRCAM cam) { (void)cam; return ROWS; }
unsigned int SR_GetCols(SRCAM cam) { (void)cam; return COLS; }

int SR_GetVersion(unsigned short version[4])
{
    version[0] = 1; version[1] = 0; version[2] = 14; version[3] = 706;
    return 0;
}

int SR_GetDeviceString(SRCAM cam, char *buffer, int length)
{
    (void)cam;
    return snprintf(buffer, (size_t)length,
                    "VendorID:0x0852, ProductID:0x0074, Manufacturer:'MESA Imaging', Product:'SR4000 (fake)'");
}

/* ---- acquisition ------------------------------------------------------------------------- */
static void settle_auto_exposure(SRCAM cam)
{
    int target = 80, now = cam->integration_time;
    if (cam->auto_exposure[0] == 255)
        return;
    cam->integration_time = (unsigned char)(now + (target - now) / 2);
}

int SR_Acquire(SRCAM cam)
{
    int r, c, images = (cam->mode & AM_CONF_MAP) ? 3 : 2;
    record("SR_Acquire");
    if (acquire_result < 0)
        return acquire_result;
    for (r = 0; r < ROWS; r++) {
        for (c = 0; c < COLS; c++) {
            distance_image[r * COLS + c] = (unsigned short)(100 * r + c + 1);
            amplitude_image[r * COLS + c] = (unsigned short)(1000 + c + 7 * cam->frames);
            confidence_image[r * COLS + c] = (unsigned short)(0xFFFF - 10 * r);
        }
    }
    cam->frames++;
    settle_auto_exposure(cam);
    return images * ROWS * COLS * 2;
}

int SR_GetImageList(SRCAM cam, ImgEntry **list)
{
    void *data[3] = {distance_image, amplitude_image, confidence_image};
    int types[3] = {0, 1, 8}, i, count = (cam->mode & AM_CONF_MAP) ? 3 : 2;
    for (i = 0; i < 3; i++) {
        entries[i].imgType = types[i];
        entries[i].dataType = 3;
        entries[i].data = data[i];
        entries[i].width = COLS;
        entries[i].height = ROWS;
    }
    *list = entries;
    return count;
}

void *SR_GetImage(SRCAM cam, unsigned char index)
{
    int count = (cam->mode & AM_CONF_MAP) ? 3 : 2;
    return index < count ? entries[index].data : 0;
}

int SR_CoordTrfFlt(SRCAM cam, float *x, float *y, float *z, int pitch_x, int pitch_y, int pitch_z)
{
    int r, c, i;
    (void)cam;
    record("SR_CoordTrfFlt %d %d %d", pitch_x, pitch_y, pitch_z);
    for (r = 0; r < ROWS; r++) {
        for (c = 0; c < COLS; c++) {
            i = r * COLS + c;
            *(float *)((char *)x + (size_t)i * pitch_x) = 0.001f * c;
            *(float *)((char *)y + (size_t)i * pitch_y) = 0.002f * r;
            *(float *)((char *)z + (size_t)i * pitch_z) = distance_image[i] * 5.0f / 65535.0f;
        }
    }
    return 0;
}
